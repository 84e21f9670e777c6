// Gradient checks of the cpu LiDAR backward pass (render/lidar/lidar_backward.h): central finite
// differences of the double-precision reference forward against the analytic gradients (double
// reference; float through LidarRenderer::Backward after the scalar and the vectorised forwards),
// relative error per parameter group, on small random scenes, static and rolling sweeps. A kScalar
// forward is followed by the scalar reference backward, a vectorised forward by the vectorised one.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_backward.h"
#include "render/lidar/lidar_renderer.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/common/finite_differences.h"
#include "tests/lidar/lidar_test_scenes.h"

namespace streetsim {
namespace {

using Scene = lidar_test::GradScene;
Scene RandomScene(unsigned seed, int n, bool rolling) { return lidar_test::RandomGradScene(seed, n, rolling); }

double LossDouble(ThreadPool& pool, const Scene& s, const GaussianStore& store, const std::vector<float>& refl) {
  LidarReferenceOutput out;
  const absl::Status st = RenderLidarReference(pool, store, s.model, s.sweep, &refl, &out);
  EXPECT_TRUE(st.ok()) << st;
  double loss = 0;
  for (size_t p = 0; p < out.alpha.size(); ++p) {
    loss += s.w_range[p] * out.range_sum[p] + s.w_alpha[p] * out.alpha[p] + s.w_intensity[p] * out.intensity_sum[p];
  }
  return loss;
}

LidarGaussianGradsT<double> AnalyticDouble(ThreadPool& pool, const Scene& s) {
  LidarReferenceOutput out;
  LidarUpstreamGradsT<double> up{s.w_range.data(), s.w_alpha.data(), s.w_intensity.data()};
  LidarGaussianGradsT<double> g;
  EXPECT_TRUE(RenderLidarReference(pool, s.store, s.model, s.sweep, &s.reflectance, &out, &up, &g).ok());
  return g;
}

LidarGaussianGradsT<double> AnalyticFloat(const Scene& s, LidarRenderOptions::Kernel kernel) {
  LidarRenderer renderer(2);
  LidarRenderOptions opt;
  opt.reflectance = &s.reflectance;
  opt.kernel = kernel;
  opt.keep_for_backward = true;
  LidarRenderOutput out;
  EXPECT_TRUE(renderer.Render(s.store, s.model, s.sweep, opt, &out).ok());
  std::vector<float> wr(s.w_range.begin(), s.w_range.end()), wa(s.w_alpha.begin(), s.w_alpha.end()),
      wi(s.w_intensity.begin(), s.w_intensity.end());
  LidarGaussianGrads g;
  const absl::Status st = renderer.Backward({wr.data(), wa.data(), wi.data()}, &g);
  EXPECT_TRUE(st.ok()) << st;
  auto to_d = [](const std::vector<float>& v) { return std::vector<double>(v.begin(), v.end()); };
  return {to_d(g.means), to_d(g.log_scales), to_d(g.rotations), to_d(g.opacity_logits), to_d(g.reflectance)};
}

struct Group {
  const char* name;
  std::vector<float> GaussianStore::*params;  // null: the reflectance vector
  std::vector<double> LidarGaussianGradsT<double>::*grads;
};
const Group kGroups[] = {
    {"means", &GaussianStore::means, &LidarGaussianGradsT<double>::means},
    {"log_scales", &GaussianStore::log_scales, &LidarGaussianGradsT<double>::log_scales},
    {"rotations", &GaussianStore::rotations, &LidarGaussianGradsT<double>::rotations},
    {"opacity_logits", &GaussianStore::opacity_logits, &LidarGaussianGradsT<double>::opacity_logits},
    {"reflectance", nullptr, &LidarGaussianGradsT<double>::reflectance}};

// Central differences for every parameter of a group; parameters whose two step sizes disagree (a
// discontinuity inside the step: a tile edge, the 1/255 cut, a pose-column flip) are left out.
std::vector<double> FiniteDiff(ThreadPool& pool, const Scene& s, const Group& group, std::vector<bool>* usable) {
  GaussianStore store = s.store;
  std::vector<float> refl = s.reflectance;
  std::vector<float>& p = group.params ? store.*(group.params) : refl;
  return testing::CentralDifferences(p, [&] { return LossDouble(pool, s, store, refl); }, usable);
}

using testing::UsableRelError;

class LidarGradCheck : public ::testing::TestWithParam<bool> {};

TEST_P(LidarGradCheck, AnalyticGradientsAgreeWithFiniteDifferences) {
  const bool rolling = GetParam();
  ThreadPool pool(2);
  const Scene s = RandomScene(rolling ? 11 : 7, 30, rolling);
  const LidarGaussianGradsT<double> g_double = AnalyticDouble(pool, s);
  const LidarGaussianGradsT<double> g_scalar = AnalyticFloat(s, LidarRenderOptions::Kernel::kScalar);
  const LidarGaussianGradsT<double> g_simd = AnalyticFloat(s, LidarRenderOptions::Kernel::kSimd);
  const LidarGaussianGradsT<double> g_avx2 = AnalyticFloat(s, LidarRenderOptions::Kernel::kSimdAvx2);
  int drawn = 0;
  for (size_t i = 0; i < g_double.opacity_logits.size(); ++i) drawn += g_double.opacity_logits[i] != 0;
  EXPECT_GE(drawn, 24);
  for (const Group& group : kGroups) {
    std::vector<bool> usable;
    const std::vector<double> fd = FiniteDiff(pool, s, group, &usable);
    size_t skipped = 0;
    for (bool b : usable) skipped += !b;
    const double e_double = UsableRelError(fd, g_double.*(group.grads), usable);
    const double e_scalar = UsableRelError(fd, g_scalar.*(group.grads), usable);
    const double e_simd = UsableRelError(fd, g_simd.*(group.grads), usable);
    const double e_avx2 = UsableRelError(fd, g_avx2.*(group.grads), usable);
    std::printf("%s %-15s rel. error: double %.2e  float scalar %.2e  float vectorised %.2e (%s) %.2e (avx2)  "
                "(%zu of %zu left out: discontinuous)\n",
                rolling ? "rolling" : "static ", group.name, e_double, e_scalar, e_simd, LidarRenderer::SimdIsa(),
                e_avx2, skipped, fd.size());
    if (getenv("GRAD_DEBUG")) {
      const std::vector<double>& an = g_double.*(group.grads);
      for (size_t i = 0; i < fd.size(); ++i)
        if (usable[i] && std::abs(fd[i] - an[i]) > 1e-3 * std::abs(fd[i]) + 1e-6)
          std::printf("   %s[%zu] fd %.6g an %.6g\n", group.name, i, fd[i], an[i]);
    }
    EXPECT_LT(skipped, fd.size() / 4 + 1) << group.name;
    EXPECT_LT(e_double, 1e-5) << group.name;
    EXPECT_LT(e_scalar, 1e-3) << group.name;
    EXPECT_LT(e_simd, 1e-3) << group.name;
    EXPECT_LT(e_avx2, 1e-3) << group.name;
  }
}

INSTANTIATE_TEST_SUITE_P(Sweeps, LidarGradCheck, ::testing::Values(false, true),
                         [](const auto& info) { return info.param ? "Rolling" : "Static"; });

// The float scalar forward and the double reference render the same image (the reference is the
// kScalar path in double).
TEST(LidarBackward, DoubleReferenceMatchesTheFloatForward) {
  ThreadPool pool(2);
  const Scene s = RandomScene(3, 200, true);
  LidarReferenceOutput ref;
  ASSERT_TRUE(RenderLidarReference(pool, s.store, s.model, s.sweep, &s.reflectance, &ref).ok());
  LidarRenderer renderer(2);
  LidarRenderOptions opt;
  opt.reflectance = &s.reflectance;
  opt.kernel = LidarRenderOptions::Kernel::kScalar;
  LidarRenderOutput out;
  ASSERT_TRUE(renderer.Render(s.store, s.model, s.sweep, opt, &out).ok());
  double max_alpha = 0, max_range = 0, sum_alpha = 0;
  for (size_t p = 0; p < ref.alpha.size(); ++p) {
    max_alpha = std::max(max_alpha, std::abs(ref.alpha[p] - out.alpha[p]));
    max_range = std::max(max_range, std::abs(ref.range_sum[p] - out.range_sum[p]));
    sum_alpha += ref.alpha[p];
  }
  EXPECT_GT(sum_alpha, 50);
  EXPECT_LT(max_alpha, 1e-4);
  EXPECT_LT(max_range, 1e-3);
}

// The vectorised backward against the scalar reference backward on a street (60k Gaussians, rays
// that saturate: the T < 1e-4 stop, which the small gradient-check scenes avoid), rolling sweep, reflectance, all three upstream gradients. The two forwards differ in
// rounding (threshold flips on a few rays), so per group the relative difference of the whole
// gradient vector is bounded, not each value.
TEST(LidarBackward, VectorisedBackwardMatchesTheScalarReference) {
  const lidar_test::StreetBackwardCase& t = lidar_test::StreetBackward();
  const GaussianStore& store = t.store;
  const std::vector<float>& refl = t.refl;
  const LidarModel& m = t.model;
  const LidarSweepPose& sweep = t.sweep;
  const size_t P = t.dr.size();
  LidarRenderer renderer(2);
  ASSERT_TRUE(renderer.Upload(store).ok());
  auto grads = [&](LidarRenderOptions::Kernel kernel, size_t* saturated) {
    LidarRenderOptions opt;
    opt.reflectance = &refl;
    opt.kernel = kernel;
    opt.keep_for_backward = true;
    LidarRenderOutput out;
    EXPECT_TRUE(renderer.Render(m, sweep, opt, &out).ok());
    *saturated = 0;
    for (float a : out.alpha) *saturated += a > 0.999f;
    LidarGaussianGrads g;
    EXPECT_TRUE(renderer.Backward(t.up(), &g).ok());
    return g;
  };
  size_t sat_ref = 0, sat = 0;
  const LidarGaussianGrads ref = grads(LidarRenderOptions::Kernel::kScalar, &sat_ref);
  EXPECT_GT(sat_ref, P / 20);  // the T < 1e-4 stop is exercised
  for (const auto kernel : {LidarRenderOptions::Kernel::kSimdAvx2, LidarRenderOptions::Kernel::kSimd}) {
    const LidarGaussianGrads g = grads(kernel, &sat);
    auto rel = [](const std::vector<float>& a, const std::vector<float>& b) {
      double num = 0, den = 0;
      for (size_t i = 0; i < a.size(); ++i) {
        num += (double(a[i]) - b[i]) * (double(a[i]) - b[i]);
        den += double(b[i]) * b[i];
      }
      return std::sqrt(num / std::max(den, 1e-300));
    };
    const double e[5] = {rel(g.means, ref.means), rel(g.log_scales, ref.log_scales), rel(g.rotations, ref.rotations),
                         rel(g.opacity_logits, ref.opacity_logits), rel(g.reflectance, ref.reflectance)};
    std::printf("vectorised vs scalar backward (%s): rel. difference means %.2e log_scales %.2e rotations %.2e "
                "opacity_logits %.2e reflectance %.2e (%zu saturated rays)\n",
                kernel == LidarRenderOptions::Kernel::kSimd ? LidarRenderer::SimdIsa() : "avx2", e[0], e[1], e[2], e[3],
                e[4], sat);
    for (double v : e) EXPECT_LT(v, 1e-2);
  }
}

// Deterministic mode: the same gradients, bit for bit, on 1 and 2 threads and across runs, for
// both backward kernels; and the fast mode (per-thread sums) agrees to rounding.
TEST(LidarBackward, DeterministicModeIsBitIdenticalAcrossRunsAndThreads) {
  SyntheticStreetOptions so;
  so.num_gaussians = 20'000;
  so.sh_degree = 0;
  const GaussianStore store = MakeSyntheticStreet(so);
  const LidarModel m = KittiHdl64e(512);
  LidarSweepPose sweep;
  sweep.T_world_from_lidar_start.translate(Eigen::Vector3d(20, 0.5, 1.73));
  sweep.T_world_from_lidar_end = sweep.T_world_from_lidar_start;
  sweep.T_world_from_lidar_end.translate(Eigen::Vector3d(1.0, 0, 0));
  const size_t P = static_cast<size_t>(m.beams()) * m.columns;
  std::vector<float> dr(P), da(P);
  for (size_t p = 0; p < P; ++p) {
    dr[p] = 0.01f * static_cast<float>(p % 7) - 0.03f;
    da[p] = 0.1f * static_cast<float>(p % 5) - 0.2f;
  }
  for (const auto kernel : {LidarRenderOptions::Kernel::kScalar, LidarRenderOptions::Kernel::kSimd}) {
    auto run = [&](int threads, bool deterministic) {
      LidarRenderer renderer(threads);
      LidarRenderOptions opt;
      opt.kernel = kernel;
      opt.keep_for_backward = true;
      LidarRenderOutput out;
      EXPECT_TRUE(renderer.Render(store, m, sweep, opt, &out).ok());
      LidarGaussianGrads g;
      EXPECT_TRUE(renderer.Backward({dr.data(), da.data(), nullptr}, &g, deterministic).ok());
      return g;
    };
    const LidarGaussianGrads a = run(1, true), b = run(2, true), c = run(2, true), f = run(2, false);
    EXPECT_EQ(a.means, b.means);
    EXPECT_EQ(b.means, c.means);
    EXPECT_EQ(a.log_scales, c.log_scales);
    EXPECT_EQ(a.rotations, c.rotations);
    EXPECT_EQ(a.opacity_logits, c.opacity_logits);
    double num = 0, den = 0;
    for (size_t i = 0; i < a.means.size(); ++i) {
      num += std::pow(double(a.means[i]) - f.means[i], 2);
      den += std::pow(double(a.means[i]), 2);
    }
    EXPECT_GT(den, 0);
    EXPECT_LT(std::sqrt(num / den), 1e-5);
  }
}

TEST(LidarBackward, NeedsAKeptForward) {
  const Scene s = RandomScene(5, 20, false);
  LidarRenderer renderer(1);
  LidarRenderOutput out;
  LidarGaussianGrads g;
  std::vector<float> d(static_cast<size_t>(s.model.beams()) * s.model.columns, 1.0f);
  EXPECT_EQ(renderer.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(renderer.Render(s.store, s.model, s.sweep, {}, &out).ok());
  EXPECT_EQ(renderer.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  LidarRenderOptions opt;
  opt.keep_for_backward = true;
  ASSERT_TRUE(renderer.Render(s.store, s.model, s.sweep, opt, &out).ok());
  ASSERT_TRUE(renderer.Backward({d.data()}, &g).ok());
  EXPECT_EQ(g.means.size(), 3 * s.store.size());
  EXPECT_EQ(g.rotations.size(), 4 * s.store.size());
  EXPECT_EQ(g.reflectance.size(), s.store.size());
  // d(sum range_sum) / d(reflectance) is 0; only range gradients flow.
  for (float v : g.reflectance) EXPECT_EQ(v, 0.0f);
  double norm = 0;
  for (float v : g.means) norm += std::abs(v);
  EXPECT_GT(norm, 0);
  ASSERT_TRUE(renderer.Upload(s.store).ok());  // a new upload invalidates the kept forward
  EXPECT_EQ(renderer.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
}

}  // namespace
}  // namespace streetsim
