// cpu backend: the vectorised kernel against the scalar float and double paths, and against
// closed-form expectations for single splats.
#include <cmath>
#include <random>

#include "gtest/gtest.h"
#include "render/cpu/cpu_engine.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim {
namespace {

PinholeCamera KittiCamera(double x_m = 0) {
  PinholeCamera cam;
  cam.width = 1242;
  cam.height = 375;
  cam.fx = cam.fy = 721.5377;
  cam.cx = 609.5593;
  cam.cy = 172.854;
  cam.T_world_from_cam = StreetCameraPose(x_m);
  return cam;
}

// Camera at the origin looking down +z (world = camera frame).
PinholeCamera AxisCamera(int w, int h, double f = 200) {
  PinholeCamera cam;
  cam.width = w;
  cam.height = h;
  cam.fx = cam.fy = f;
  cam.cx = (w - 1) / 2.0;
  cam.cy = (h - 1) / 2.0;
  return cam;
}

GaussianStore OneSplat(Eigen::Vector3f mean, float sigma_m, float opacity, Eigen::Vector3f rgb) {
  GaussianStore s;
  s.sh_degree = 0;
  s.Resize(1);
  for (int k = 0; k < 3; ++k) {
    s.means[k] = mean[k];
    s.log_scales[k] = std::log(sigma_m);
    s.sh[k] = (rgb[k] - 0.5f) / 0.28209479177387814f;
  }
  s.rotations = {1, 0, 0, 0};
  s.opacity_logits[0] = std::log(opacity / (1 - opacity));
  return s;
}

RenderOutput RenderWith(CpuPrecision precision, const GaussianStore& store,
                        const PinholeCamera& cam, Eigen::Vector3f bg = Eigen::Vector3f::Zero()) {
  auto engine = CreateCpuEngine({.precision = precision});
  auto scene = engine->Upload(store);
  EXPECT_TRUE(scene.ok()) << scene.status();
  RenderOutput out;
  RenderOptions options;
  options.background = bg;
  absl::Status s = engine->Render(**scene, cam, options, &out);
  EXPECT_TRUE(s.ok()) << s;
  return out;
}

struct Diff {
  double max_abs = 0;
  double frac_over = 0;  // fraction of values differing by more than tol
};
Diff Compare(const std::vector<float>& a, const std::vector<float>& b, double tol) {
  EXPECT_EQ(a.size(), b.size());
  Diff d;
  size_t over = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) {
    const double e = std::abs(double(a[i]) - double(b[i]));
    d.max_abs = std::max(d.max_abs, e);
    over += e > tol;
  }
  d.frac_over = a.empty() ? 0 : double(over) / a.size();
  return d;
}

TEST(CpuRender, SimdMatchesScalarOnStreetScene) {
  const GaussianStore store = MakeSyntheticStreet({.num_gaussians = 60'000, .seed = 7});
  const PinholeCamera cam = KittiCamera(10);
  const RenderOutput simd = RenderWith(CpuPrecision::kFloatSimd, store, cam, {0.1f, 0.2f, 0.3f});
  const RenderOutput scalar = RenderWith(CpuPrecision::kFloatScalar, store, cam, {0.1f, 0.2f, 0.3f});
  EXPECT_GT(simd.stats.num_visible, 10'000u);
  EXPECT_EQ(simd.stats.num_tile_instances, scalar.stats.num_tile_instances);
  // Only the exp differs (polynomial vs libm): tiny differences, except the rare pixel where a
  // threshold (alpha 1/255, T 1e-4) flips.
  const Diff rgb = Compare(simd.rgb, scalar.rgb, 1e-4);
  EXPECT_LT(rgb.frac_over, 1e-3);
  EXPECT_LT(Compare(simd.alpha, scalar.alpha, 1e-4).frac_over, 1e-3);
  EXPECT_LT(Compare(simd.depth, scalar.depth, 1e-3).frac_over, 1e-3);
}

TEST(CpuRender, FloatMatchesDoubleOnRandomCameras) {
  std::mt19937 rng(3);
  const GaussianStore store = MakeSyntheticStreet({.num_gaussians = 20'000, .seed = 11, .sh_degree = 2});
  for (int trial = 0; trial < 4; ++trial) {
    PinholeCamera cam = KittiCamera(std::uniform_real_distribution<double>(-5, 60)(rng));
    cam.width = 97 + 131 * trial;  // not multiples of 16
    cam.height = 61 + 37 * trial;
    cam.cx = cam.width * std::uniform_real_distribution<double>(0.3, 0.7)(rng);
    cam.cy = cam.height * std::uniform_real_distribution<double>(0.3, 0.7)(rng);
    cam.fx = cam.fy = 0.8 * cam.width;
    const RenderOutput f = RenderWith(CpuPrecision::kFloatSimd, store, cam);
    const RenderOutput d = RenderWith(CpuPrecision::kDouble, store, cam);
    EXPECT_LT(Compare(f.rgb, d.rgb, 2e-3).frac_over, 5e-3) << "trial " << trial;
    EXPECT_LT(Compare(f.alpha, d.alpha, 2e-3).frac_over, 5e-3) << "trial " << trial;
  }
}

TEST(CpuRender, SingleSplatMatchesClosedForm) {
  // Isotropic splat 10 m ahead, sigma 0.1 m, focal 200 px: sigma_px^2 = (200*0.1/10)^2 + 0.3.
  const float o = 0.6f;
  const GaussianStore store = OneSplat({0, 0, 10}, 0.1f, o, {0.8f, 0.4f, 0.2f});
  const PinholeCamera cam = AxisCamera(65, 65);  // centre pixel (32, 32) on the axis
  for (CpuPrecision p : {CpuPrecision::kFloatSimd, CpuPrecision::kDouble}) {
    const RenderOutput out = RenderWith(p, store, cam);
    const double var_px = 4.0 + 0.3;
    for (int du : {0, 1, 3, 5}) {
      const size_t pix = 32 * 65 + 32 + du;
      const double a = o * std::exp(-0.5 * du * du / var_px);
      if (a < 1.0 / 255) continue;
      EXPECT_NEAR(out.alpha[pix], a, 1e-5) << du;
      EXPECT_NEAR(out.rgb[pix * 3 + 0], 0.8 * a, 1e-5);
      EXPECT_NEAR(out.rgb[pix * 3 + 2], 0.2 * a, 1e-5);
      EXPECT_NEAR(out.depth[pix], 10 * a, 1e-4);
    }
    EXPECT_EQ(out.alpha[0], 0.0f);  // far corner: below 1/255
  }
}

TEST(CpuRender, NearerSplatOccludesRegardlessOfIndexOrder) {
  GaussianStore store = OneSplat({0, 0, 20}, 0.5f, 0.99f, {1, 0, 0});  // far, red, index 0
  GaussianStore near = OneSplat({0, 0, 5}, 0.5f, 0.99f, {0, 1, 0});    // near, green, index 1
  store.Resize(2);
  for (int k = 0; k < 3; ++k) {
    store.means[3 + k] = near.means[k];
    store.log_scales[3 + k] = near.log_scales[k];
    store.sh[3 + k] = near.sh[k];
  }
  store.rotations = {1, 0, 0, 0, 1, 0, 0, 0};
  store.opacity_logits[1] = near.opacity_logits[0];
  const RenderOutput out = RenderWith(CpuPrecision::kFloatSimd, store, AxisCamera(33, 33));
  const size_t c = 16 * 33 + 16;
  EXPECT_GT(out.rgb[c * 3 + 1], 0.98f);  // green in front
  EXPECT_LT(out.rgb[c * 3 + 0], 0.01f);
}

TEST(CpuRender, BackgroundAndEmptyScene) {
  GaussianStore empty;
  const RenderOutput out = RenderWith(CpuPrecision::kFloatSimd, empty, AxisCamera(40, 20), {0.25f, 0.5f, 1.0f});
  ASSERT_EQ(out.rgb.size(), 40u * 20 * 3);
  for (size_t p = 0; p < 40 * 20; ++p) {
    EXPECT_EQ(out.rgb[p * 3 + 0], 0.25f);
    EXPECT_EQ(out.rgb[p * 3 + 2], 1.0f);
    EXPECT_EQ(out.alpha[p], 0.0f);
    EXPECT_EQ(out.depth[p], 0.0f);
  }
}

TEST(CpuRender, CullsBehindAndAtNearPlane) {
  for (float z : {-5.0f, 0.0f, 0.15f, 0.2f}) {
    const GaussianStore store = OneSplat({0, 0, z}, 0.05f, 0.9f, {1, 1, 1});
    const RenderOutput out = RenderWith(CpuPrecision::kFloatSimd, store, AxisCamera(32, 32));
    EXPECT_EQ(out.stats.num_visible, 0u) << z;
  }
  const RenderOutput out =
      RenderWith(CpuPrecision::kFloatSimd, OneSplat({0, 0, 0.25f}, 0.05f, 0.9f, {1, 1, 1}), AxisCamera(32, 32));
  EXPECT_EQ(out.stats.num_visible, 1u);
}

TEST(CpuRender, TransmittanceStopsAtThreshold) {
  // 200 opaque splats stacked on the axis: every pixel stops before T falls below 1e-4.
  GaussianStore store;
  store.Resize(200);
  for (int i = 0; i < 200; ++i) {
    store.means[i * 3 + 2] = 2.0f + 0.1f * i;
    for (int k = 0; k < 3; ++k) store.log_scales[i * 3 + k] = std::log(1.0f);
    store.rotations[i * 4] = 1;
    store.opacity_logits[i] = 3.0f;
  }
  const RenderOutput out = RenderWith(CpuPrecision::kFloatSimd, store, AxisCamera(48, 32));
  for (float a : out.alpha) {
    EXPECT_LE(a, 1.0f - 1e-4f + 1e-7f);
    EXPECT_GT(a, 0.99f);
  }
}

TEST(CpuRender, PrincipalPointShiftsImage) {
  const GaussianStore store = MakeSyntheticStreet({.num_gaussians = 5'000, .seed = 5});
  PinholeCamera cam = KittiCamera(0);
  cam.width = 320;
  cam.height = 160;
  cam.fx = cam.fy = 250;
  cam.cx = 150;
  cam.cy = 80;
  const RenderOutput a = RenderWith(CpuPrecision::kFloatSimd, store, cam);
  cam.cx += 7;
  const RenderOutput b = RenderWith(CpuPrecision::kFloatSimd, store, cam);
  // Same image, moved 7 px right. Only splats whose centres lie far off-screen change: the EWA
  // Jacobian clamp is relative to the principal point, so their footprints differ slightly.
  size_t differ = 0, total = 0;
  for (int v = 20; v < 140; ++v)
    for (int u = 30; u < 280; ++u, ++total)
      differ += std::abs(a.alpha[v * 320 + u] - b.alpha[v * 320 + u + 7]) > 1e-4f;
  EXPECT_LT(double(differ) / total, 0.01);
  // And the shift is real: unshifted pixels do differ.
  size_t unshifted = 0;
  for (int v = 20; v < 140; ++v)
    for (int u = 30; u < 280; ++u) unshifted += std::abs(a.alpha[v * 320 + u] - b.alpha[v * 320 + u]) > 1e-4f;
  EXPECT_GT(double(unshifted) / total, 0.1);
}

TEST(CpuRender, RejectsBadCamerasAndScenes) {
  auto engine = CreateCpuEngine();
  auto scene = engine->Upload(OneSplat({0, 0, 5}, 0.1f, 0.5f, {1, 1, 1}));
  ASSERT_TRUE(scene.ok());
  RenderOutput out;
  PinholeCamera cam = AxisCamera(64, 64);
  auto expect_invalid = [&](PinholeCamera c) {
    EXPECT_EQ(engine->Render(**scene, c, {}, &out).code(), absl::StatusCode::kInvalidArgument);
  };
  PinholeCamera c = cam; c.width = 0; expect_invalid(c);
  c = cam; c.height = 4097; expect_invalid(c);
  c = cam; c.fx = std::nan(""); expect_invalid(c);
  c = cam; c.fy = -1; expect_invalid(c);
  c = cam; c.cx = INFINITY; expect_invalid(c);
  c = cam; c.T_world_from_cam.matrix()(0, 0) = 2; expect_invalid(c);
  c = cam; c.T_world_from_cam.matrix()(1, 3) = std::nan(""); expect_invalid(c);
  RenderOptions bad_bg;
  bad_bg.background = {NAN, 0, 0};
  EXPECT_EQ(engine->Render(**scene, cam, bad_bg, &out).code(), absl::StatusCode::kInvalidArgument);

  GaussianStore bad = OneSplat({0, 0, 5}, 0.1f, 0.5f, {1, 1, 1});
  bad.means[1] = NAN;
  EXPECT_EQ(engine->Upload(bad).status().code(), absl::StatusCode::kInvalidArgument);
  bad = OneSplat({0, 0, 5}, 0.1f, 0.5f, {1, 1, 1});
  bad.rotations = {0, 0, 0, 0};
  EXPECT_EQ(engine->Upload(bad).status().code(), absl::StatusCode::kInvalidArgument);
  bad = OneSplat({0, 0, 5}, 0.1f, 0.5f, {1, 1, 1});
  bad.sh.pop_back();
  EXPECT_EQ(engine->Upload(bad).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(CpuRender, ExtremeButFiniteSplatsDoNotBreakTheFrame) {
  // Huge scales, tiny scales, splats grazing the near plane and far off-screen: the frame must
  // render, stay finite and bounded.
  GaussianStore store;
  store.Resize(6);
  const float means[6][3] = {{0, 0, 5}, {0, 0, 0.21f}, {1e6f, 0, 5}, {0, 0, 1e7f}, {3, 1, 2}, {-1, 0, 3}};
  const float ls[6] = {20.0f, -20.0f, 0.0f, 5.0f, 0.0f, -3.0f};
  for (int i = 0; i < 6; ++i) {
    for (int k = 0; k < 3; ++k) {
      store.means[i * 3 + k] = means[i][k];
      store.log_scales[i * 3 + k] = ls[i];
    }
    store.rotations[i * 4] = 1;
    store.opacity_logits[i] = 2;
  }
  for (CpuPrecision p : {CpuPrecision::kFloatSimd, CpuPrecision::kDouble}) {
    const RenderOutput out = RenderWith(p, store, AxisCamera(200, 100));
    for (float v : out.rgb) ASSERT_TRUE(std::isfinite(v) && v >= 0);
    for (float v : out.alpha) ASSERT_TRUE(v >= 0 && v <= 1);
  }
}

}  // namespace
}  // namespace streetsim
