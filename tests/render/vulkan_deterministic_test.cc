// The vulkan backward's deterministic mode (BackwardOptions::deterministic, docs/rendering.md
// "Deterministic mode"): on a street scene with hundreds of splats listed per tile (where two
// atomic backward passes on lavapipe already differ in some floats' last bits), the gradients
// repeat bit for bit across backward calls on one kept forward, across forwards, across two
// freshly created engines (devices) and across the packed and pair tile-instance layouts; they
// agree with the atomic backward and the cpu backward. ctest also runs it at lavapipe subgroup sizes 4 and 16. The gradient checks
// of the mode (vs the cpu backward, vs finite differences) live in vulkan_backward_test.cc.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <memory>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/cpu/cpu_engine.h"
#include "render/vulkan/testing.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim {
namespace {

std::unique_ptr<Engine> NewEngine() {
  absl::StatusOr<std::unique_ptr<Engine>> vk = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
  return vk.ok() ? *std::move(vk) : nullptr;
}

struct Problem {
  GaussianStore store;
  PinholeCamera cam;
  std::vector<float> g_rgb, g_depth, g_alpha;
};

// 30k street Gaussians seen by a 400x128 KITTI-like camera: ~20k visible, hundreds listed per
// tile near the horizon.
const Problem& Street() {
  static const Problem* p = [] {
    auto* q = new Problem;
    q->store = MakeSyntheticStreet({.num_gaussians = 30000, .seed = 11, .sh_degree = 3});
    q->cam.width = 400;
    q->cam.height = 128;
    q->cam.fx = q->cam.fy = 721.5377 * 400 / 1242.0;
    q->cam.cx = (400 - 1) / 2.0;
    q->cam.cy = (128 - 1) / 2.0;
    q->cam.T_world_from_cam = StreetCameraPose(12.0);
    const size_t pixels = size_t{400} * 128;
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> u(-1, 1);
    for (auto [v, n, scale] : {std::tuple{&q->g_rgb, pixels * 3, 1e-3f},
                               std::tuple{&q->g_depth, pixels, 1e-4f},
                               std::tuple{&q->g_alpha, pixels, 1e-3f}}) {
      v->resize(n);
      for (float& x : *v) x = u(rng) * scale;
    }
    return q;
  }();
  return *p;
}

struct Passes {
  std::vector<GaussianGrads> grads;  // one per backward call
  RenderStats stats;
};

// `forwards` forwards, each followed by `backwards` backward passes.
Passes RenderAndBackward(Engine& engine, bool deterministic, int forwards = 1, int backwards = 1) {
  const Problem& p = Street();
  Passes run;
  auto scene = engine.Upload(p.store);
  EXPECT_TRUE(scene.ok()) << scene.status();
  if (!scene.ok()) return run;
  RenderOptions opt;
  opt.keep_for_backward = true;
  for (int f = 0; f < forwards; ++f) {
    RenderOutput out;
    const absl::Status st = engine.Render(**scene, p.cam, opt, &out);
    EXPECT_TRUE(st.ok()) << st;
    if (!st.ok()) return run;
    run.stats = out.stats;
    for (int b = 0; b < backwards; ++b) {
      GaussianGrads g;
      const absl::Status bs = engine.RenderBackward(
          **scene, {p.g_rgb.data(), p.g_depth.data(), p.g_alpha.data()},
          {.deterministic = deterministic}, &g);
      EXPECT_TRUE(bs.ok()) << bs;
      run.grads.push_back(std::move(g));
    }
  }
  return run;
}

using Field = std::vector<float> GaussianGrads::*;
const std::pair<const char*, Field> kFields[] = {
    {"means", &GaussianGrads::means},           {"log_scales", &GaussianGrads::log_scales},
    {"rotations", &GaussianGrads::rotations},   {"opacity_logits", &GaussianGrads::opacity_logits},
    {"sh", &GaussianGrads::sh},                 {"means2d", &GaussianGrads::means2d},
    {"radii", &GaussianGrads::radii}};

// Number of floats whose bits differ (size mismatch: all of them).
size_t BitDifferences(const std::vector<float>& a, const std::vector<float>& b) {
  if (a.size() != b.size()) return std::max(a.size(), b.size()) + 1;
  size_t n = 0;
  for (size_t i = 0; i < a.size(); ++i) n += std::memcmp(&a[i], &b[i], sizeof(float)) != 0;
  return n;
}

void ExpectIdenticalBits(const GaussianGrads& a, const GaussianGrads& b, const char* what) {
  for (const auto& [name, field] : kFields) {
    EXPECT_EQ(BitDifferences(a.*field, b.*field), 0u) << name << ": " << what;
  }
}

double RelError(const std::vector<float>& ref, const std::vector<float>& x) {
  double num = 0, den = 0;
  for (size_t i = 0; i < std::min(ref.size(), x.size()); ++i) {
    num += (double(ref[i]) - x[i]) * (double(ref[i]) - x[i]);
    den += double(ref[i]) * ref[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

class VulkanDeterministic : public testing::Test {
 protected:
  static void SetUpTestSuite() { engine_ = NewEngine().release(); }
  void SetUp() override {
    if (engine_ == nullptr) GTEST_SKIP() << "no Vulkan device on this machine";
  }
  static Engine* engine_;
};
Engine* VulkanDeterministic::engine_ = nullptr;

TEST_F(VulkanDeterministic, IdenticalBitsAcrossCallsForwardsAndEngines) {
  std::printf("subgroup size %u, %s\n", vulkan_testing::SubgroupSize(*engine_),
              engine_->device_name().c_str());
  // Two forwards, two backward passes on each kept forward.
  const Passes a = RenderAndBackward(*engine_, true, 2, 2);
  ASSERT_EQ(a.grads.size(), 4u);
  std::printf("street: %zu Gaussians, %zu visible, %zu tile instances\n", a.stats.num_gaussians,
              a.stats.num_visible, a.stats.num_tile_instances);
  EXPECT_GT(a.stats.num_tile_instances, 3 * a.stats.num_visible / 2);  // splats overlap tiles
  size_t nonzero = 0;
  for (float v : a.grads[0].means) nonzero += v != 0.0f;
  EXPECT_GT(nonzero, a.stats.num_visible);  // the gradients are not trivially equal
  ExpectIdenticalBits(a.grads[0], a.grads[1], "second backward on the kept forward");
  ExpectIdenticalBits(a.grads[0], a.grads[2], "backward of a second forward");
  ExpectIdenticalBits(a.grads[0], a.grads[3], "second backward of the second forward");

  // A fresh engine (its own VkDevice, pipelines and buffers).
  std::unique_ptr<Engine> fresh = NewEngine();
  ASSERT_NE(fresh, nullptr);
  const Passes b = RenderAndBackward(*fresh, true);
  ASSERT_EQ(b.grads.size(), 1u);
  ExpectIdenticalBits(a.grads[0], b.grads[0], "fresh engine");

  // Pair mode lists the same instances in the same order: the same bits.
  vulkan_testing::ForcePairMode(*fresh, true);
  const Passes c = RenderAndBackward(*fresh, true);
  vulkan_testing::ForcePairMode(*fresh, false);
  ASSERT_EQ(c.grads.size(), 1u);
  ExpectIdenticalBits(a.grads[0], c.grads[0], "pair mode");
}

TEST_F(VulkanDeterministic, AgreesWithAtomicBackward) {
  const Passes det = RenderAndBackward(*engine_, true);
  const Passes atomic = RenderAndBackward(*engine_, false, 1, 2);
  auto cpu_engine = CreateCpuEngine();
  const Passes cpu = RenderAndBackward(*cpu_engine, false);
  ASSERT_EQ(det.grads.size(), 1u);
  ASSERT_EQ(atomic.grads.size(), 2u);
  ASSERT_EQ(cpu.grads.size(), 1u);
  for (const auto& [name, field] : kFields) {
    const double e = RelError(atomic.grads[0].*field, det.grads[0].*field);
    const double e_cpu = RelError(cpu.grads[0].*field, det.grads[0].*field);
    std::printf("%-15s vs cpu: atomic %.2e deterministic %.2e\n", name,
                RelError(cpu.grads[0].*field, atomic.grads[0].*field), e_cpu);
    EXPECT_LT(e_cpu, 1e-4) << name;
    // Informational: whether the atomics reordered between two calls on this device.
    const size_t flips = BitDifferences(atomic.grads[0].*field, atomic.grads[1].*field);
    std::printf("%-15s deterministic vs atomic rel. error %.2e; atomic run to run: %zu of %zu "
                "floats differ\n",
                name, e, flips, (atomic.grads[0].*field).size());
    EXPECT_LT(e, 1e-5) << name;
  }
  EXPECT_EQ(det.grads[0].radii, atomic.grads[0].radii);
}

}  // namespace
}  // namespace streetsim
