// Gradient checks of the cpu backward pass: central finite differences of the double-precision
// forward (projection + blend in double) against the engines' analytic gradients (double, scalar
// float, vectorised float), relative error per parameter group, on small random scenes.
#include <cmath>
#include <cstdio>
#include <random>

#include "gtest/gtest.h"
#include "render/cpu/binning.h"
#include "render/cpu/blend.h"
#include "render/cpu/cpu_engine.h"
#include "render/cpu/project.h"
#include "tests/common/finite_differences.h"
#include "tests/common/grad_check_scene.h"

namespace streetsim {
namespace {

using gradcheck::LossDouble;
using gradcheck::RandomScene;
using gradcheck::Scene;

GaussianGrads Analytic(CpuPrecision precision, const Scene& s, bool deterministic = false, int threads = 0) {
  auto engine = CreateCpuEngine({.num_threads = threads, .precision = precision});
  auto scene = engine->Upload(s.store);
  EXPECT_TRUE(scene.ok());
  RenderOptions opt;
  opt.background = s.background;
  opt.keep_for_backward = true;
  RenderOutput out;
  EXPECT_TRUE(engine->Render(**scene, s.cam, opt, &out).ok());
  std::vector<float> g_rgb(s.w_rgb.begin(), s.w_rgb.end()), g_d(s.w_depth.begin(), s.w_depth.end()),
      g_a(s.w_alpha.begin(), s.w_alpha.end());
  GaussianGrads grads;
  BackwardOptions bo;
  bo.deterministic = deterministic;
  absl::Status st = engine->RenderBackward(**scene, {g_rgb.data(), g_d.data(), g_a.data()}, bo, &grads);
  EXPECT_TRUE(st.ok()) << st;
  return grads;
}

struct Group {
  const char* name;
  std::vector<float> GaussianStore::*params;
  std::vector<float> GaussianGrads::*grads;
};
const Group kGroups[] = {{"means", &GaussianStore::means, &GaussianGrads::means},
                         {"log_scales", &GaussianStore::log_scales, &GaussianGrads::log_scales},
                         {"rotations", &GaussianStore::rotations, &GaussianGrads::rotations},
                         {"opacity_logits", &GaussianStore::opacity_logits, &GaussianGrads::opacity_logits},
                         {"sh", &GaussianStore::sh, &GaussianGrads::sh}};

// Central differences for every parameter of a group; parameters whose two step sizes disagree
// (a discontinuity inside the step: a tile edge, the 1/255 cut) are left out and counted.
std::vector<double> FiniteDiff(ThreadPool& pool, const Scene& s, const Group& group, std::vector<bool>* usable) {
  GaussianStore store = s.store;
  return testing::CentralDifferences(store.*(group.params), [&] { return LossDouble(pool, s, store); }, usable);
}

using testing::UsableRelError;

class GradCheck : public ::testing::TestWithParam<int> {};

TEST_P(GradCheck, AllBackendsAgreeWithFiniteDifferences) {
  const int degree = GetParam();
  ThreadPool pool(0);
  const Scene s = RandomScene(17 + degree, 24, degree);
  const GaussianGrads g_double = Analytic(CpuPrecision::kDouble, s);
  const GaussianGrads g_scalar = Analytic(CpuPrecision::kFloatScalar, s);
  const GaussianGrads g_simd = Analytic(CpuPrecision::kFloatSimd, s);
  int visible = 0;
  for (float r : g_double.radii) visible += r > 0;
  EXPECT_GE(visible, 18);
  for (const Group& group : kGroups) {
    std::vector<bool> usable;
    const std::vector<double> fd = FiniteDiff(pool, s, group, &usable);
    size_t skipped = 0;
    for (bool b : usable) skipped += !b;
    const double e_double = UsableRelError(fd, g_double.*(group.grads), usable);
    const double e_scalar = UsableRelError(fd, g_scalar.*(group.grads), usable);
    const double e_simd = UsableRelError(fd, g_simd.*(group.grads), usable);
    std::printf("degree %d %-15s rel. error: double %.2e  float scalar %.2e  float simd %.2e  (%zu of %zu "
                "left out: discontinuous)\n",
                degree, group.name, e_double, e_scalar, e_simd, skipped, fd.size());
    if (getenv("GRAD_DEBUG")) {
      const std::vector<float>& an = g_double.*(group.grads);
      for (size_t i = 0; i < fd.size(); ++i)
        if (usable[i] && std::abs(fd[i] - an[i]) > 1e-3 * std::abs(fd[i]) + 1e-6)
          std::printf("   %s[%zu] fd %.6g an %.6g\n", group.name, i, fd[i], an[i]);
    }
    EXPECT_LT(skipped, fd.size() / 4 + 1) << group.name;  // the 1/255 cut and tile edges
    EXPECT_LT(e_double, 1e-5) << group.name;
    EXPECT_LT(e_scalar, 2e-5) << group.name;
    EXPECT_LT(e_simd, 2e-5) << group.name;
  }
  // The 2D-mean gradient (densification statistic) agrees across precisions.
  double num = 0, den = 0;
  for (size_t i = 0; i < g_double.means2d.size(); ++i) {
    num += std::pow(g_double.means2d[i] - g_simd.means2d[i], 2);
    den += std::pow(g_double.means2d[i], 2);
  }
  EXPECT_LT(std::sqrt(num / den), 2e-3);
  EXPECT_EQ(g_double.radii, g_simd.radii);
}

INSTANTIATE_TEST_SUITE_P(ShDegrees, GradCheck, ::testing::Values(0, 1, 3));

TEST(GradCheck, DeterministicModeIsBitIdenticalAcrossRunsAndThreads) {
  const Scene s = RandomScene(5, 300, 3, 160, 120);
  const GaussianGrads a = Analytic(CpuPrecision::kFloatSimd, s, true, 1);
  const GaussianGrads b = Analytic(CpuPrecision::kFloatSimd, s, true, 2);
  const GaussianGrads c = Analytic(CpuPrecision::kFloatSimd, s, true, 2);
  EXPECT_EQ(a.means, b.means);
  EXPECT_EQ(b.means, c.means);
  EXPECT_EQ(a.sh, c.sh);
  EXPECT_EQ(a.opacity_logits, c.opacity_logits);
  EXPECT_EQ(a.log_scales, c.log_scales);
  EXPECT_EQ(a.rotations, c.rotations);
  // And it agrees with the fast (per-thread arrays) mode to rounding.
  const GaussianGrads f = Analytic(CpuPrecision::kFloatSimd, s, false, 2);
  double num = 0, den = 0;
  for (size_t i = 0; i < a.means.size(); ++i) {
    num += std::pow(a.means[i] - f.means[i], 2);
    den += std::pow(a.means[i], 2);
  }
  EXPECT_LT(std::sqrt(num / den), 1e-5);
}

TEST(GradCheck, BackwardWithoutKeptForwardIsAnError) {
  const Scene s = RandomScene(3, 10, 0);
  auto engine = CreateCpuEngine();
  auto scene = engine->Upload(s.store);
  ASSERT_TRUE(scene.ok());
  RenderOutput out;
  ASSERT_TRUE(engine->Render(**scene, s.cam, {}, &out).ok());
  std::vector<float> g(out.rgb.size(), 1.0f);
  GaussianGrads grads;
  EXPECT_EQ(engine->RenderBackward(**scene, {g.data()}, {}, &grads).code(), absl::StatusCode::kFailedPrecondition);
}

}  // namespace
}  // namespace streetsim
