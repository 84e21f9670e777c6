// The vulkan backward pass (render/vulkan/backward.cc): gradients against the cpu backward
// (relative error per parameter group, small random scenes, SH 0..3, odd image sizes) and
// against central finite differences of the cpu double-precision forward (the approach of
// tests/train/grad_check_test.cc), with float atomics and with the compare-and-swap fallback.
// ctest also runs it at lavapipe subgroup sizes 4 and 16 (LP_NATIVE_VECTOR_WIDTH=128 / 512).
//
// STREETSIM_BWD_BENCH=1 adds the timing of the setting (648x420, 139k Gaussians).
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <random>

#include "gtest/gtest.h"
#include "render/cpu/binning.h"
#include "render/cpu/blend.h"
#include "render/cpu/cpu_engine.h"
#include "render/cpu/project.h"
#include "render/vulkan/testing.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/common/finite_differences.h"
#include "tests/common/grad_check_scene.h"
#include "tests/common/needle_splats.h"

namespace streetsim {
namespace {

Engine* Vulkan() {
  static Engine* e = [] {
    absl::StatusOr<std::unique_ptr<Engine>> vk = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    return vk.ok() ? vk->release() : nullptr;
  }();
  return e;
}

// A second engine created without VK_EXT_shader_atomic_float: the compare-and-swap blend backward.
Engine* VulkanCas() {
  static Engine* e = [] {
    setenv("STREETSIM_VK_NO_FLOAT_ATOMICS", "1", 1);
    absl::StatusOr<std::unique_ptr<Engine>> vk = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    unsetenv("STREETSIM_VK_NO_FLOAT_ATOMICS");
    return vk.ok() ? vk->release() : nullptr;
  }();
  return e;
}

using gradcheck::LossDouble;
using gradcheck::RandomScene;
using gradcheck::Scene;

GaussianGrads Analytic(Engine& engine, const Scene& s, bool with_depth_alpha = true,
                       bool deterministic = false) {
  auto scene = engine.Upload(s.store);
  EXPECT_TRUE(scene.ok()) << scene.status();
  if (!scene.ok()) return {};
  RenderOptions opt;
  opt.background = s.background;
  opt.keep_for_backward = true;
  RenderOutput out;
  absl::Status st = engine.Render(**scene, s.cam, opt, &out);
  EXPECT_TRUE(st.ok()) << st;
  std::vector<float> g_rgb(s.w_rgb.begin(), s.w_rgb.end()), g_d(s.w_depth.begin(), s.w_depth.end()),
      g_a(s.w_alpha.begin(), s.w_alpha.end());
  GaussianGrads grads;
  RenderOutputGrads og{g_rgb.data(), with_depth_alpha ? g_d.data() : nullptr,
                       with_depth_alpha ? g_a.data() : nullptr};
  st = engine.RenderBackward(**scene, og, {.deterministic = deterministic}, &grads);
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

double RelError(const std::vector<float>& ref, const std::vector<float>& x) {
  EXPECT_EQ(ref.size(), x.size());
  double num = 0, den = 0;
  for (size_t i = 0; i < std::min(ref.size(), x.size()); ++i) {
    num += (double(ref[i]) - x[i]) * (double(ref[i]) - x[i]);
    den += double(ref[i]) * ref[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

class VulkanBackward : public ::testing::Test {
 protected:
  void SetUp() override {
    if (Vulkan() == nullptr) GTEST_SKIP() << "no Vulkan device on this machine";
  }
};

struct Case {
  int degree, n, width, height;
};

// Against the cpu backward (vectorised float and double) on the same scene: both follow the same
// rules in float and differ in exp/rounding and summation order; a threshold (1/255, T 1e-4)
// flipping at one pixel moves a gradient slightly.
TEST_F(VulkanBackward, AgreesWithCpuBackward) {
  const Case cases[] = {{0, 60, 73, 41}, {1, 80, 101, 67}, {2, 50, 47, 95}, {3, 120, 129, 77}};
  auto cpu_double = CreateCpuEngine({.precision = CpuPrecision::kDouble});
  auto cpu_simd = CreateCpuEngine();
  std::printf("subgroup size %u, %s\n", vulkan_testing::SubgroupSize(*Vulkan()),
              Vulkan()->device_name().c_str());
  for (const Case& c : cases) {
    const Scene s = RandomScene(31 + c.degree, c.n, c.degree, c.width, c.height);
    const GaussianGrads ref = Analytic(*cpu_double, s);
    const GaussianGrads simd = Analytic(*cpu_simd, s);
    const GaussianGrads vk = Analytic(*Vulkan(), s);
    const GaussianGrads det = Analytic(*Vulkan(), s, true, /*deterministic=*/true);
    for (const Group& g : kGroups) {
      const double e_vk = RelError(ref.*(g.grads), vk.*(g.grads));
      const double e_det = RelError(ref.*(g.grads), det.*(g.grads));
      const double e_simd = RelError(ref.*(g.grads), simd.*(g.grads));
      std::printf("degree %d %dx%d %-15s rel. error vs cpu double: vulkan %.2e  deterministic "
                  "%.2e  cpu simd %.2e\n",
                  c.degree, c.width, c.height, g.name, e_vk, e_det, e_simd);
      EXPECT_LT(e_vk, 3e-5) << g.name << " degree " << c.degree;
      EXPECT_LT(e_det, 3e-5) << g.name << " degree " << c.degree << " deterministic";
    }
    EXPECT_EQ(ref.radii, det.radii);
    const double e2d = RelError(ref.means2d, vk.means2d);
    std::printf("degree %d %dx%d %-15s rel. error vs cpu double: vulkan %.2e\n", c.degree, c.width,
                c.height, "means2d", e2d);
    EXPECT_LT(e2d, 3e-5);
    EXPECT_EQ(ref.radii, vk.radii);
  }
}

// Needle splats (one axis kilometres long, the others millimetres, what an unbounded decoder
// Δlog-scale produced in training): the float projection and its backward must neither cancel
// nor overflow (render/common/projection_math.h: ProjectCovariance), on the GPU as on the cpu.
TEST_F(VulkanBackward, NeedleSplatsAgreeWithCpuDouble) {
  auto cpu_double = CreateCpuEngine({.precision = CpuPrecision::kDouble});
  Scene s = RandomScene(91, 240, 1, 96, 64);
  std::mt19937 rng(91);
  testing::MakeNeedles(7.5f, 2.5f, rng, &s.store);
  auto cpu_simd = CreateCpuEngine();
  const GaussianGrads ref = Analytic(*cpu_double, s);
  const GaussianGrads simd = Analytic(*cpu_simd, s);
  const GaussianGrads vk = Analytic(*Vulkan(), s);
  int visible = 0;
  for (float r : ref.radii) visible += r > 0;
  EXPECT_GE(visible, 60);
  for (const Group& g : kGroups) {
    const std::vector<float>& v = vk.*(g.grads);
    EXPECT_EQ(std::count_if(v.begin(), v.end(), [](float x) { return !std::isfinite(x); }), 0) << g.name;
    const double e = RelError(ref.*(g.grads), v);
    const double e_simd = RelError(ref.*(g.grads), simd.*(g.grads));
    std::printf("needles %-15s rel. error vs cpu double: vulkan %.2e  cpu simd %.2e\n", g.name, e, e_simd);
    // Float's own error on needles is ~1e-2 on both backends (the blend's quadratic form of a
    // near-degenerate conic); the cancelling chain this guards against gave 1e4 or inf.
    EXPECT_LT(e, 0.1) << g.name;
    EXPECT_LT(e_simd, 0.1) << g.name;
  }
}

void CheckFiniteDifferences(bool deterministic) {
  ThreadPool pool(0);
  for (int degree : {0, 1, 3}) {
    const Scene s = RandomScene(17 + degree, 24, degree, 72, 56);
    const GaussianGrads vk = Analytic(*Vulkan(), s, /*with_depth_alpha=*/true, deterministic);
    int visible = 0;
    for (float r : vk.radii) visible += r > 0;
    EXPECT_GE(visible, 18);
    for (const Group& group : kGroups) {
      GaussianStore store = s.store;
      std::vector<float>& p = store.*(group.params);
      std::vector<bool> usable;
      const std::vector<double> fd =
          testing::CentralDifferences(p, [&] { return LossDouble(pool, s, store); }, &usable);
      const size_t skipped = std::count(usable.begin(), usable.end(), false);
      const double e = testing::UsableRelError(fd, vk.*(group.grads), usable);
      std::printf("degree %d %-15s vulkan%s rel. error vs finite differences %.2e (%zu of %zu left out)\n",
                  degree, group.name, deterministic ? " deterministic" : "", e, skipped, p.size());
      EXPECT_LT(skipped, p.size() / 4 + 1) << group.name;
      EXPECT_LT(e, 2e-5) << group.name << " degree " << degree;
    }
  }
}

// Thousands of faint splats in one or three tiles: long walks per tile (llvmpipe ends an
// invocation's loops after 65535 trips in total, which a per-batch loop over the subgroups
// exceeded at subgroup size 4, and a per-block loop at 8), against the atomic and cpu backwards.
TEST_F(VulkanBackward, DeterministicLongTileLists) {
  auto cpu_double = CreateCpuEngine({.precision = CpuPrecision::kDouble});
  for (int width : {16, 48}) {
    Scene s = RandomScene(5, 3000, 0, width, 16);
    for (float& o : s.store.opacity_logits) o -= 3.0f;  // opacity 0.01..0.15: long n_contrib
    const GaussianGrads ref = Analytic(*cpu_double, s);
    const GaussianGrads atomic = Analytic(*Vulkan(), s);
    const GaussianGrads det = Analytic(*Vulkan(), s, true, /*deterministic=*/true);
    for (const Group& g : kGroups) {
      const double e_atomic = RelError(ref.*(g.grads), atomic.*(g.grads));
      const double e_det = RelError(ref.*(g.grads), det.*(g.grads));
      std::printf("3000 faint, %dx16 %-15s rel. error vs cpu double: atomic %.2e deterministic "
                  "%.2e\n", width, g.name, e_atomic, e_det);
      EXPECT_LT(e_det, 3e-5) << g.name << " width " << width;
      EXPECT_LT(RelError(atomic.*(g.grads), det.*(g.grads)), 1e-5) << g.name;
    }
  }
}

TEST_F(VulkanBackward, AgreesWithFiniteDifferences) { CheckFiniteDifferences(false); }
TEST_F(VulkanBackward, DeterministicAgreesWithFiniteDifferences) { CheckFiniteDifferences(true); }

TEST_F(VulkanBackward, CompareAndSwapFallbackAgrees) {
  Engine* cas = VulkanCas();
  ASSERT_NE(cas, nullptr);
  EXPECT_NE(cas->device_name().find("no float atomics"), std::string::npos) << cas->device_name();
  const Scene s = RandomScene(7, 150, 3, 97, 63);
  const GaussianGrads a = Analytic(*Vulkan(), s);
  const GaussianGrads b = Analytic(*cas, s);
  for (const Group& g : kGroups) EXPECT_LT(RelError(a.*(g.grads), b.*(g.grads)), 1e-5) << g.name;
  EXPECT_EQ(a.radii, b.radii);
}

TEST_F(VulkanBackward, NullDepthAndAlphaGradsMeanZero) {
  const Scene s = RandomScene(9, 40, 1, 61, 45);
  Scene s0 = s;
  std::fill(s0.w_depth.begin(), s0.w_depth.end(), 0.0);
  std::fill(s0.w_alpha.begin(), s0.w_alpha.end(), 0.0);
  const GaussianGrads a = Analytic(*Vulkan(), s, /*with_depth_alpha=*/false);
  const GaussianGrads b = Analytic(*Vulkan(), s0);
  for (const Group& g : kGroups) EXPECT_LT(RelError(b.*(g.grads), a.*(g.grads)), 1e-6) << g.name;
}

TEST_F(VulkanBackward, PreconditionsAndUpdateScene) {
  Engine& vk = *Vulkan();
  const Scene s = RandomScene(3, 30, 2, 50, 40);
  auto scene = vk.Upload(s.store);
  ASSERT_TRUE(scene.ok());
  RenderOutput out;
  ASSERT_TRUE(vk.Render(**scene, s.cam, {}, &out).ok());
  std::vector<float> g(out.rgb.size(), 1.0f);
  GaussianGrads grads;
  // Without keep_for_backward.
  EXPECT_EQ(vk.RenderBackward(**scene, {g.data()}, {}, &grads).code(),
            absl::StatusCode::kFailedPrecondition);
  RenderOptions keep;
  keep.keep_for_backward = true;
  ASSERT_TRUE(vk.Render(**scene, s.cam, keep, &out).ok());
  EXPECT_EQ(vk.RenderBackward(**scene, {nullptr}, {}, &grads).code(),
            absl::StatusCode::kInvalidArgument);
  BackwardOptions det;
  det.deterministic = true;
  GaussianGrads det_grads;
  EXPECT_TRUE(vk.RenderBackward(**scene, {g.data()}, det, &det_grads).ok());
  // More slot bytes than the (test-lowered) storage buffer range: a clear ResourceExhausted.
  vulkan_testing::SetDeterministicSlotLimit(vk, 64);
  const absl::Status big = vk.RenderBackward(**scene, {g.data()}, det, &grads);
  vulkan_testing::SetDeterministicSlotLimit(vk, 0);
  EXPECT_EQ(big.code(), absl::StatusCode::kResourceExhausted) << big;
  EXPECT_NE(big.message().find("deterministic"), std::string::npos) << big;
  EXPECT_TRUE(vk.RenderBackward(**scene, {g.data()}, {}, &grads).ok());
  EXPECT_LT(RelError(grads.means, det_grads.means), 1e-5);
  // Backward may run twice on one kept forward (same result up to atomics order).
  GaussianGrads again;
  EXPECT_TRUE(vk.RenderBackward(**scene, {g.data()}, {}, &again).ok());
  EXPECT_LT(RelError(grads.means, again.means), 1e-5);

  // UpdateScene in place: renders what a fresh upload of the new parameters renders, and the
  // kept forward is invalidated.
  GaussianStore moved = s.store;
  for (float& m : moved.means) m += 0.01f;
  const DeviceScene* before = scene->get();
  ASSERT_TRUE(vk.UpdateScene(moved, &*scene).ok());
  EXPECT_EQ(scene->get(), before);
  EXPECT_EQ(vk.RenderBackward(**scene, {g.data()}, {}, &grads).code(),
            absl::StatusCode::kFailedPrecondition);
  RenderOutput updated, fresh;
  ASSERT_TRUE(vk.Render(**scene, s.cam, {}, &updated).ok());
  auto fresh_scene = vk.Upload(moved);
  ASSERT_TRUE(fresh_scene.ok());
  ASSERT_TRUE(vk.Render(**fresh_scene, s.cam, {}, &fresh).ok());
  EXPECT_EQ(updated.rgb, fresh.rgb);
  // A different size re-uploads.
  moved.Resize(20);
  ASSERT_TRUE(vk.UpdateScene(moved, &*scene).ok());
  EXPECT_EQ((*scene)->size(), 20u);
  EXPECT_EQ(vulkan_testing::ValidationMessages(vk), 0);  // 0 unless validation is on
}

TEST_F(VulkanBackward, Benchmark) {
  if (std::getenv("STREETSIM_BWD_BENCH") == nullptr) GTEST_SKIP() << "STREETSIM_BWD_BENCH=1";
  const GaussianStore street = MakeSyntheticStreet({.num_gaussians = 139000, .seed = 3, .sh_degree = 3});
  PinholeCamera cam;
  cam.width = 648;
  cam.height = 420;
  cam.fx = cam.fy = 721.5377 * 648 / 1242.0;
  cam.cx = (648 - 1) / 2.0;
  cam.cy = (420 - 1) / 2.0;
  cam.T_world_from_cam = StreetCameraPose(10.0);
  const size_t pix = size_t{648} * 420;
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> u(-1, 1);
  std::vector<float> g_rgb(pix * 3), g_d(pix), g_a(pix);
  for (float& v : g_rgb) v = u(rng) * 1e-3f;
  for (float& v : g_d) v = u(rng) * 1e-4f;
  for (float& v : g_a) v = u(rng) * 1e-3f;
  auto cpu = CreateCpuEngine();
  GaussianGrads results[2];
  Engine* engines[2] = {cpu.get(), Vulkan()};
  for (int e = 0; e < 2; ++e) {
    Engine& engine = *engines[e];
    auto scene = engine.Upload(street);
    ASSERT_TRUE(scene.ok());
    RenderOptions opt;
    opt.keep_for_backward = true;
    RenderOutput out;
    std::vector<double> fwd, bwd;
    for (int it = 0; it < 4; ++it) {
      ASSERT_TRUE(engine.Render(**scene, cam, opt, &out).ok());
      ASSERT_TRUE(engine.RenderBackward(**scene, {g_rgb.data(), g_d.data(), g_a.data()}, {},
                                        &results[e]).ok());
      if (it > 0) {
        fwd.push_back(out.timings.total_ms);
        bwd.push_back(results[e].backward_ms);
      }
    }
    std::sort(fwd.begin(), fwd.end());
    std::sort(bwd.begin(), bwd.end());
    std::printf("%s: 648x420, 139k Gaussians (%zu visible, %zu instances): forward %.1f ms, "
                "backward %.1f ms (median of %zu)\n",
                engine.device_name().c_str(), out.stats.num_visible, out.stats.num_tile_instances,
                fwd[fwd.size() / 2], bwd[bwd.size() / 2], bwd.size());
  }
  for (const Group& g : kGroups) {
    std::printf("street %-15s rel. error vulkan vs cpu %.2e\n", g.name,
                RelError(results[0].*(g.grads), results[1].*(g.grads)));
  }
}

}  // namespace
}  // namespace streetsim
