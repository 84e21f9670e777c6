// The two production backends against each other: the vulkan backend (lavapipe in CI) must draw
// what the cpu backend draws, on street-like scenes, random scenes and the shared trained PLYs.
#include <algorithm>
#include <cmath>
#include <random>

#include "gtest/gtest.h"
#include "render/cpu/cpu_engine.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/ply_io.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim {
namespace {

struct Engines {
  std::unique_ptr<Engine> cpu, vulkan;
};

Engines& Get() {
  static Engines* e = [] {
    auto* engines = new Engines;
    engines->cpu = CreateCpuEngine();
    absl::StatusOr<std::unique_ptr<Engine>> vk = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    if (vk.ok()) engines->vulkan = std::move(*vk);
    return engines;
  }();
  return *e;
}

struct Renders {
  RenderOutput cpu, vulkan;
};

Renders RenderBoth(const GaussianStore& store, const PinholeCamera& cam, Eigen::Vector3f bg) {
  Renders r;
  RenderOptions options;
  options.background = bg;
  for (auto [engine, out] : {std::pair{Get().cpu.get(), &r.cpu}, std::pair{Get().vulkan.get(), &r.vulkan}}) {
    auto scene = engine->Upload(store);
    EXPECT_TRUE(scene.ok()) << scene.status();
    if (!scene.ok()) continue;
    absl::Status s = engine->Render(**scene, cam, options, out);
    EXPECT_TRUE(s.ok()) << engine->device_name() << ": " << s;
  }
  return r;
}

// Both backends follow the same rules in float; they differ in exp/log/sqrt implementations and
// operation order, so values agree closely except where a threshold (alpha 1/255, T 1e-4) flips
// for one splat at one pixel, which changes what lies behind it at that pixel.
void ExpectAgree(const Renders& r, const std::string& what) {
  ASSERT_EQ(r.cpu.rgb.size(), r.vulkan.rgb.size()) << what;
  ASSERT_EQ(r.cpu.alpha.size(), r.vulkan.alpha.size()) << what;
  const size_t pixels = r.cpu.alpha.size();
  size_t bad_rgb = 0, bad_alpha = 0, bad_depth = 0;
  double sum_abs = 0;
  for (size_t p = 0; p < pixels; ++p) {
    for (int c = 0; c < 3; ++c) {
      const double e = std::abs(r.cpu.rgb[p * 3 + c] - r.vulkan.rgb[p * 3 + c]);
      sum_abs += e;
      bad_rgb += e > 2e-3;
    }
    bad_alpha += std::abs(r.cpu.alpha[p] - r.vulkan.alpha[p]) > 2e-3;
    const double dd = std::abs(r.cpu.depth[p] - r.vulkan.depth[p]);
    bad_depth += dd > 2e-3 * std::max(1.0f, std::abs(r.cpu.depth[p]));
  }
  EXPECT_LT(sum_abs / (pixels * 3.0), 1e-4) << what << ": mean |rgb difference|";
  EXPECT_LE(bad_rgb, pixels * 3 / 500 + 3) << what;
  EXPECT_LE(bad_alpha, pixels / 500 + 1) << what;
  EXPECT_LE(bad_depth, pixels / 500 + 1) << what;
  const double vis_cpu = r.cpu.stats.num_visible, vis_vk = r.vulkan.stats.num_visible;
  EXPECT_LE(std::abs(vis_cpu - vis_vk), 1e-3 * vis_cpu + 2) << what << ": visible counts";
}

class BackendAgreement : public testing::Test {
 protected:
  void SetUp() override {
    if (!Get().vulkan) GTEST_SKIP() << "no Vulkan device on this machine";
  }
};

TEST_F(BackendAgreement, StreetSceneAlongTheStreet) {
  const GaussianStore store = MakeSyntheticStreet({.num_gaussians = 60'000, .seed = 21});
  PinholeCamera cam;
  cam.width = 1242;
  cam.height = 375;
  cam.fx = cam.fy = 721.5377;
  cam.cx = 609.5593;
  cam.cy = 172.854;
  for (double x : {0.0, 17.0, 40.0}) {
    cam.T_world_from_cam = StreetCameraPose(x, x / 20);
    ExpectAgree(RenderBoth(store, cam, {0.2f, 0.3f, 0.4f}), "street at x=" + std::to_string(x));
  }
}

TEST_F(BackendAgreement, RandomScenesOddSizesAndAllShDegrees) {
  std::mt19937 rng(99);
  for (int degree = 0; degree <= 3; ++degree) {
    const GaussianStore store =
        MakeSyntheticStreet({.num_gaussians = 8'000, .seed = 100u + degree, .sh_degree = degree});
    PinholeCamera cam;
    cam.width = 97 + 211 * degree;
    cam.height = 61 + 53 * degree;
    cam.fx = cam.fy = std::uniform_real_distribution<double>(0.5, 1.5)(rng) * cam.width;
    cam.cx = cam.width * std::uniform_real_distribution<double>(0.2, 0.8)(rng);
    cam.cy = cam.height * std::uniform_real_distribution<double>(0.2, 0.8)(rng);
    cam.T_world_from_cam = StreetCameraPose(std::uniform_real_distribution<double>(-10, 60)(rng), 1.0);
    ExpectAgree(RenderBoth(store, cam, {0, 0, 0}), "degree " + std::to_string(degree));
  }
}

// A camera outside the scene's robust bounds looking at its centre (as streetsim ply-info does).
PinholeCamera FrameScene(const GaussianStore& store, Eigen::Vector3d forward, Eigen::Vector3d down) {
  Eigen::Vector3d lo, hi;
  for (int k = 0; k < 3; ++k) {
    std::vector<float> axis(store.size());
    for (size_t i = 0; i < store.size(); ++i) axis[i] = store.means[i * 3 + k];
    std::sort(axis.begin(), axis.end());
    lo[k] = axis[axis.size() / 20];
    hi[k] = axis[axis.size() * 19 / 20];
  }
  PinholeCamera cam;
  cam.width = 400;
  cam.height = 300;
  cam.fx = cam.fy = 346.4;
  cam.cx = 199.5;
  cam.cy = 149.5;
  Eigen::Matrix3d R;
  R.col(2) = forward;
  R.col(1) = down;
  R.col(0) = down.cross(forward);
  cam.T_world_from_cam.linear() = R;
  cam.T_world_from_cam.translation() = 0.5 * (lo + hi) - 1.9 * (hi - lo).norm() * forward;
  return cam;
}

TEST_F(BackendAgreement, SharedTrainedPlys) {
  for (const char* name : {"inria_sh3_9080.ply", "mip_sh0_45624.ply"}) {
    absl::StatusOr<GaussianStore> store = ReadGaussianPly(std::string(STREETSIM_DATA_DIR) + "/ply/" + name);
    ASSERT_TRUE(store.ok()) << store.status();
    ExpectAgree(RenderBoth(*store, FrameScene(*store, {0, 0, 1}, {0, 1, 0}), {0, 0, 0}), name);
    ExpectAgree(RenderBoth(*store, FrameScene(*store, {1, 0, 0}, {0, 1, 0}), {1, 1, 1}), name);
  }
}

}  // namespace
}  // namespace streetsim
