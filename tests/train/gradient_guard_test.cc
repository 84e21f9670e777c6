// The trainer's guard against non-finite gradients (scene/train/gradient_guard.h): rows with a nan
// or inf anywhere are zeroed and counted, every other row is left bit for bit, and too many such
// rows is an error that names the iteration.
#include "scene/train/gradient_guard.h"

#include <cmath>
#include <limits>
#include <random>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace streetsim::train {
namespace {

GaussianGrads RandomGrads(size_t n, int sh_coeffs, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> d(0.0f, 1.0f);
  GaussianGrads g;
  auto fill = [&](std::vector<float>& v, size_t width) {
    v.resize(n * width);
    for (float& x : v) x = d(rng);
  };
  fill(g.means, 3);
  fill(g.log_scales, 3);
  fill(g.rotations, 4);
  fill(g.opacity_logits, 1);
  fill(g.sh, static_cast<size_t>(sh_coeffs) * 3);
  fill(g.means2d, 2);
  return g;
}

TEST(GradientGuard, ZeroesExactlyTheRowsWithANonFiniteValue) {
  constexpr size_t n = 10'000;
  ThreadPool pool(2);
  const GaussianGrads clean = RandomGrads(n, 16, 3);
  GaussianGrads g = clean;
  const float inf = std::numeric_limits<float>::infinity();
  // One bad value per row, in a different array each time (the last SH coefficient, the screen mean).
  g.means[4321 * 3 + 2] = std::nanf("");
  g.log_scales[17 * 3] = inf;
  g.rotations[9999 * 4 + 3] = -inf;
  g.opacity_logits[5000] = std::nanf("");
  g.sh[777 * 48 + 47] = std::nanf("");
  g.means2d[8888 * 2 + 1] = inf;
  const NonFiniteRows bad = ZeroNonFiniteGradientRows(n, &g, pool);
  EXPECT_EQ(bad.rows, 6u);
  EXPECT_EQ(bad.first_row, 17);
  for (size_t i : {size_t{17}, size_t{777}, size_t{4321}, size_t{5000}, size_t{8888}, size_t{9999}}) {
    for (int k = 0; k < 3; ++k) EXPECT_EQ(g.means[i * 3 + k], 0.0f) << i;
    for (int k = 0; k < 3; ++k) EXPECT_EQ(g.log_scales[i * 3 + k], 0.0f) << i;
    for (int k = 0; k < 4; ++k) EXPECT_EQ(g.rotations[i * 4 + k], 0.0f) << i;
    EXPECT_EQ(g.opacity_logits[i], 0.0f) << i;
    for (int k = 0; k < 48; ++k) EXPECT_EQ(g.sh[i * 48 + k], 0.0f) << i;
    for (int k = 0; k < 2; ++k) EXPECT_EQ(g.means2d[i * 2 + k], 0.0f) << i;
  }
  // Every other row untouched.
  size_t changed = 0;
  for (size_t i = 0; i < n; ++i) changed += (g.opacity_logits[i] != clean.opacity_logits[i]);
  EXPECT_EQ(changed, 6u);
  EXPECT_EQ(g.means[4322 * 3], clean.means[4322 * 3]);
  EXPECT_EQ(g.sh[778 * 48], clean.sh[778 * 48]);
}

TEST(GradientGuard, CleanGradientsAreLeftAlone) {
  ThreadPool pool(2);
  const GaussianGrads clean = RandomGrads(1'000, 4, 5);
  GaussianGrads g = clean;
  const NonFiniteRows bad = ZeroNonFiniteGradientRows(1'000, &g, pool);
  EXPECT_EQ(bad.rows, 0u);
  EXPECT_EQ(bad.first_row, -1);
  EXPECT_EQ(g.sh, clean.sh);
  EXPECT_EQ(g.means, clean.means);
  EXPECT_TRUE(GuardGradients(7, 1'000, 0.01, &g, pool).ok());
}

TEST(GradientGuard, ManyNonFiniteRowsAreDivergence) {
  ThreadPool pool(2);
  GaussianGrads g = RandomGrads(1'000, 1, 9);
  for (size_t i = 0; i < 10; ++i) g.means[i * 100 * 3] = std::nanf("");  // 1 %: tolerated
  EXPECT_TRUE(GuardGradients(41, 1'000, 0.01, &g, pool).ok());
  for (size_t i = 0; i < 11; ++i) g.means[(i * 90 + 1) * 3] = std::nanf("");  // 1.1 %: diverged
  const absl::Status s = GuardGradients(42, 1'000, 0.01, &g, pool);
  EXPECT_EQ(s.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(std::string(s.message()), ::testing::HasSubstr("diverged at iteration 42: 11 of 1000 Gaussians"));
}

}  // namespace
}  // namespace streetsim::train
