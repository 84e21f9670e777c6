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

// A network's gradient: finite passes untouched; one nan or inf anywhere (several chunks of the
// parallel scan, the first of them reported) stops the run with the iteration and the index.
TEST(GradientGuard, NonFiniteNetworkGradientIsAnError) {
  ThreadPool pool(2);
  std::vector<float> g(1'000'003);
  std::mt19937 rng(11);
  std::normal_distribution<float> d(0.0f, 1e30f);  // huge but finite
  for (float& x : g) x = d(rng);
  const std::vector<float> clean = g;
  EXPECT_TRUE(CheckFiniteNetworkGradient(5, "deformation field", g.data(), g.size(), pool).ok());
  EXPECT_EQ(g, clean);
  g[999'999] = std::numeric_limits<float>::infinity();
  g[700'001] = -std::numeric_limits<float>::infinity();
  g[300'017] = std::nanf("");
  const absl::Status s = CheckFiniteNetworkGradient(77, "field extension", g.data(), g.size(), pool);
  EXPECT_EQ(s.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(std::string(s.message()),
              ::testing::HasSubstr("diverged at fine iteration 77: the field extension's gradient is not finite "
                                   "(first at parameter 300017 of 1000003)"));
  g[300'017] = 0.0f;
  g[700'001] = 0.0f;
  EXPECT_THAT(std::string(CheckFiniteNetworkGradient(78, "x", g.data(), g.size(), pool).message()),
              ::testing::HasSubstr("first at parameter 999999 "));
  g[999'999] = 0.0f;
  g.back() = std::nanf("");  // the tail chunk
  EXPECT_FALSE(CheckFiniteNetworkGradient(79, "x", g.data(), g.size(), pool).ok());
  EXPECT_TRUE(CheckFiniteNetworkGradient(80, "x", g.data(), 0, pool).ok());
}

}  // namespace
}  // namespace streetsim::train
