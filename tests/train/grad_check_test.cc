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

namespace streetsim {
namespace {

struct Scene {
  GaussianStore store;
  PinholeCamera cam;
  Eigen::Vector3f background;
  std::vector<double> w_rgb, w_depth, w_alpha;  // the loss: sum of w . outputs
};

Scene RandomScene(unsigned seed, int n, int degree, int width = 72, int height = 56) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  Scene s;
  s.cam.width = width;
  s.cam.height = height;
  s.cam.fx = 60;
  s.cam.fy = 64;
  s.cam.cx = width * 0.47;
  s.cam.cy = height * 0.53;
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() = Eigen::AngleAxisd(0.1, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
  pose.translation() = Eigen::Vector3d(0.2, -0.1, -0.3);
  s.cam.T_world_from_cam = pose;
  s.background = Eigen::Vector3f(0.2f, 0.5f, 0.1f);
  GaussianStore& g = s.store;
  g.sh_degree = degree;
  g.Resize(n);
  const int K = g.sh_coeffs();
  for (int i = 0; i < n; ++i) {
    const double z = 2.5 + 3.0 * u(rng);
    const Eigen::Vector3d p_cam((u(rng) - 0.5) * 1.1 * z * width / s.cam.fx, (u(rng) - 0.5) * 1.1 * z * height / s.cam.fy, z);
    const Eigen::Vector3d p = pose * p_cam;
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = static_cast<float>(p[k]);
      g.log_scales[i * 3 + k] = std::log(0.04f + 0.12f * u(rng));
    }
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = u(rng) - 0.5f + (k == 0 ? 0.6f : 0.0f);
    g.opacity_logits[i] = -1.5f + 2.5f * u(rng);  // opacity 0.18..0.73: below the 0.99 clamp
    for (int k = 0; k < K * 3; ++k) g.sh[i * K * 3 + k] = (k < 3 ? 1.2f : 0.35f) * (u(rng) - 0.5f);
  }
  const size_t pix = static_cast<size_t>(width) * height;
  for (size_t i = 0; i < pix * 3; ++i) s.w_rgb.push_back(u(rng) - 0.3);
  for (size_t i = 0; i < pix; ++i) s.w_depth.push_back(0.1 * (u(rng) - 0.5));
  for (size_t i = 0; i < pix; ++i) s.w_alpha.push_back(u(rng) - 0.5);
  return s;
}

// The loss through the double-precision forward (cpu internals, no float outputs in between).
double LossDouble(ThreadPool& pool, const Scene& s, const GaussianStore& store) {
  cpu::Frame<double> f;
  const auto cam = cpu::MakeCameraParams<double>(s.cam);
  f.width = s.cam.width;
  f.height = s.cam.height;
  f.tiles_x = cam.tiles_x;
  f.tiles_y = cam.tiles_y;
  cpu::ProjectGaussians<double>(pool, store, cam, &f);
  cpu::SortByDepth(&f);
  cpu::BinTiles(pool, &f);
  const size_t pix = static_cast<size_t>(f.width) * f.height;
  std::vector<double> rgb(pix * 3), depth(pix), alpha(pix);
  cpu::BlendArgs<double> args;
  args.frame = &f;
  for (int c = 0; c < 3; ++c) args.background[c] = s.background[c];
  args.rgb = rgb.data();
  args.depth = depth.data();
  args.alpha = alpha.data();
  cpu::BlendScalar<double>(pool, args);
  double loss = 0;
  for (size_t i = 0; i < pix * 3; ++i) loss += s.w_rgb[i] * rgb[i];
  for (size_t i = 0; i < pix; ++i) loss += s.w_depth[i] * depth[i] + s.w_alpha[i] * alpha[i];
  return loss;
}

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
  std::vector<float>& p = store.*(group.params);
  std::vector<double> fd(p.size());
  usable->assign(p.size(), true);
  for (size_t i = 0; i < p.size(); ++i) {
    const float x = p[i];
    auto diff = [&](double h) {
      const float xp = static_cast<float>(x + h), xm = static_cast<float>(x - h);
      p[i] = xp;
      const double lp = LossDouble(pool, s, store);
      p[i] = xm;
      const double lm = LossDouble(pool, s, store);
      p[i] = x;
      return (lp - lm) / (double(xp) - double(xm));  // the steps actually taken (float grid)
    };
    const double h = 1e-4 * std::max(1.0, std::abs(double(x)));
    const double d1 = diff(h), d2 = diff(h / 4);
    fd[i] = d2;
    if (std::abs(d1 - d2) > 0.02 * std::max(std::abs(d2), 1e-3)) (*usable)[i] = false;
  }
  return fd;
}

double RelError(const std::vector<double>& fd, const std::vector<float>& an, const std::vector<bool>& usable) {
  double num = 0, den = 0;
  for (size_t i = 0; i < fd.size(); ++i) {
    if (!usable[i]) continue;
    num += (fd[i] - an[i]) * (fd[i] - an[i]);
    den += fd[i] * fd[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

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
    const double e_double = RelError(fd, g_double.*(group.grads), usable);
    const double e_scalar = RelError(fd, g_scalar.*(group.grads), usable);
    const double e_simd = RelError(fd, g_simd.*(group.grads), usable);
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
