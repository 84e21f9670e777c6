// Tests of the vulkan backend (render/vulkan): the scan and radix sort stages against simple C++
// references, and whole frames against a scalar 3DGS reference (vulkan_reference.h).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <numeric>
#include <random>
#include <string>
#include <vector>

#include "render/engine.h"
#include "render/vulkan/testing.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/common/params_view.h"
#include "tests/render/vulkan_reference.h"

namespace streetsim {
namespace {

using ::testing::HasSubstr;
using testing::MakeCamera;
using testing::MakeRandomScene;
using testing::RenderReference;
using testing::SceneOptions;

// One engine for the whole binary: pipeline creation dominates a small test on lavapipe.
Engine& SharedEngine() {
  static Engine* engine = [] {
    auto created = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    if (!created.ok()) {
      ADD_FAILURE() << "no vulkan engine: " << created.status();
      return static_cast<Engine*>(nullptr);
    }
    return created->release();
  }();
  if (engine == nullptr) std::abort();
  return *engine;
}

class VulkanTest : public ::testing::Test {
 protected:
  void TearDown() override {
    // Non-zero only when validation is on (Debug builds) and the layer complained.
    EXPECT_EQ(vulkan_testing::ValidationMessages(SharedEngine()), 0);
  }
};

// --- Device selection --------------------------------------------------------------------------

TEST_F(VulkanTest, ListsDevices) {
  const std::vector<VulkanDeviceInfo> devices = ListVulkanDevices();
  ASSERT_FALSE(devices.empty());
  bool any_gpu = false;
  for (const auto& d : devices) {
    EXPECT_FALSE(d.name.empty());
    EXPECT_GE(d.subgroup_size, 1u);
    any_gpu |= !d.is_cpu;
  }
  EXPECT_EQ(HasVulkanGpu(), any_gpu);
  EXPECT_THAT(SharedEngine().device_name(), HasSubstr("vulkan: "));
  EXPECT_EQ(SharedEngine().backend(), Backend::kVulkan);
  EXPECT_GE(vulkan_testing::SubgroupSize(SharedEngine()), 1u);
}

class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old, had_ = true;
    setenv(name, value, 1);
  }
  ~ScopedEnv() {
    if (had_) {
      setenv(name_, old_.c_str(), 1);
    } else {
      unsetenv(name_);
    }
  }

 private:
  const char* name_;
  std::string old_;
  bool had_ = false;
};

TEST_F(VulkanTest, DeviceNameThatMatchesNothingIsAClearError) {
  {
    ScopedEnv env("STREETSIM_VK_DEVICE", "no-such-device-xyz");
    auto engine = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    ASSERT_FALSE(engine.ok());
    EXPECT_EQ(engine.status().code(), absl::StatusCode::kFailedPrecondition);
    EXPECT_THAT(engine.status().message(), HasSubstr("no-such-device-xyz"));
    EXPECT_THAT(engine.status().message(), HasSubstr("found: [0] "));
  }
  {
    ScopedEnv env("STREETSIM_VK_DEVICE", "999");
    auto engine = CreateVulkanEngine(VulkanDevicePreference::kGpu);
    ASSERT_FALSE(engine.ok());
    EXPECT_EQ(engine.status().code(), absl::StatusCode::kFailedPrecondition);
  }
  {
    // By index and by case-insensitive name substring.
    const std::vector<VulkanDeviceInfo> devices = ListVulkanDevices();
    ASSERT_FALSE(devices.empty());
    std::string upper = devices[0].name.substr(0, 4);
    for (char& c : upper) c = static_cast<char>(std::toupper(c));
    ScopedEnv env("STREETSIM_VK_DEVICE", upper.c_str());
    auto engine = CreateVulkanEngine(VulkanDevicePreference::kGpu);
    ASSERT_TRUE(engine.ok()) << engine.status();
  }
}

TEST_F(VulkanTest, NoDriverIsAClearErrorNotACrash) {
  // The loader scans for drivers at every instance creation; point it at nothing.
  ScopedEnv icd("VK_ICD_FILENAMES", "/nonexistent/streetsim_no_icd.json");
  ScopedEnv driver("VK_DRIVER_FILES", "/nonexistent/streetsim_no_icd.json");
  EXPECT_TRUE(ListVulkanDevices().empty());
  EXPECT_FALSE(HasVulkanGpu());
  auto engine = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
  ASSERT_FALSE(engine.ok());
  EXPECT_EQ(engine.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(engine.status().message(), HasSubstr("vulkan"));
}

// --- Prefix sum ----------------------------------------------------------------------------------

std::vector<uint32_t> RandomValues(size_t n, uint32_t max_value, uint32_t seed) {
  std::mt19937 rng(seed);
  std::vector<uint32_t> v(n);
  for (auto& x : v) x = std::uniform_int_distribution<uint32_t>(0, max_value)(rng);
  return v;
}

TEST_F(VulkanTest, ExclusiveScanMatchesReference) {
  uint32_t seed = 7;
  for (size_t n : {size_t{1}, size_t{255}, size_t{256}, size_t{1023}, size_t{1024}, size_t{1025},
                   size_t{100000}, size_t{(1 << 20) + 7}}) {
    for (bool indirect : {false, true}) {
      SCOPED_TRACE(::testing::Message() << "n=" << n << " indirect=" << indirect);
      const std::vector<uint32_t> in = RandomValues(n, 40, ++seed);
      std::vector<uint32_t> expected(n);
      std::exclusive_scan(in.begin(), in.end(), expected.begin(), 0u);
      uint32_t total = 0;
      auto out = vulkan_testing::ExclusiveScan(SharedEngine(), in, indirect, false, &total);
      ASSERT_TRUE(out.ok()) << out.status();
      EXPECT_EQ(total, expected.back() + in.back());
      ASSERT_EQ(out->size(), n);
      EXPECT_TRUE(*out == expected);
    }
  }
}

TEST_F(VulkanTest, ExclusiveScanBeyondOneDimensionalGrids) {
  // More than 16384 blocks of 1024: the level-0 grid goes 2D (pipeline.h: GridFor). 2^25 - 3
  // elements also come close to lavapipe's 128 MiB maxStorageBufferRange.
  const size_t n = (size_t{1} << 25) - 3;
  std::vector<uint32_t> in(n);
  for (size_t i = 0; i < n; ++i) in[i] = static_cast<uint32_t>((i * 2654435761u) >> 29);
  uint32_t total = 0;
  auto out = vulkan_testing::ExclusiveScan(SharedEngine(), in, /*indirect=*/true, false, &total);
  ASSERT_TRUE(out.ok()) << out.status();
  uint32_t acc = 0;
  size_t mismatches = 0;
  for (size_t i = 0; i < n; ++i) {
    mismatches += (*out)[i] != acc;
    acc += in[i];
  }
  EXPECT_EQ(mismatches, 0u);
  EXPECT_EQ(total, acc);
}

TEST_F(VulkanTest, SaturatingScanClampsInsteadOfWrapping) {
  std::vector<uint32_t> in(3000, 1);
  in[10] = 0x80000000u;
  in[2000] = 0x80000000u;
  uint32_t total = 0;
  auto out = vulkan_testing::ExclusiveScan(SharedEngine(), in, true, true, &total);
  ASSERT_TRUE(out.ok()) << out.status();
  EXPECT_EQ(total, 0xffffffffu);
  EXPECT_EQ((*out)[11], 0x80000000u + 10u);
  EXPECT_EQ((*out)[2999], 0xffffffffu);
}

// --- Radix sort ----------------------------------------------------------------------------------

TEST_F(VulkanTest, RadixSortIsStableAndCorrect) {
  struct Case {
    size_t n;
    int bits;
    uint32_t key_modulus;  // 0: full 32-bit keys; else many duplicates
  };
  uint32_t seed = 100;
  for (const Case& c : {Case{1, 32, 0}, Case{7, 32, 0}, Case{4095, 32, 17}, Case{4096, 32, 0},
                        Case{4097, 11, 0}, Case{100000, 32, 1000}, Case{100000, 12, 0},
                        Case{33333, 5, 0}, Case{(1 << 20) + 7, 32, 0}}) {
    SCOPED_TRACE(::testing::Message() << "n=" << c.n << " bits=" << c.bits);
    std::mt19937 rng(++seed);
    std::vector<uint32_t> keys(c.n), vals(c.n);
    for (size_t i = 0; i < c.n; ++i) {
      keys[i] = rng();
      if (c.key_modulus) keys[i] %= c.key_modulus;
      vals[i] = static_cast<uint32_t>(i);
    }
    const uint32_t mask = c.bits >= 32 ? ~0u : (1u << c.bits) - 1;
    // Keys above `bits` must not influence the order: the stable sort is by (key & mask).
    std::vector<uint32_t> order(c.n);
    std::iota(order.begin(), order.end(), 0u);
    std::stable_sort(order.begin(), order.end(),
                     [&](uint32_t a, uint32_t b) { return (keys[a] & mask) < (keys[b] & mask); });
    std::vector<uint32_t> gpu_keys = keys, gpu_vals = vals;
    if (c.bits < 32) {
      for (auto& k : gpu_keys) k &= mask;  // the frame only sorts keys that fit the bits
    }
    ASSERT_TRUE(vulkan_testing::SortPairs(SharedEngine(), c.bits, &gpu_keys, &gpu_vals).ok());
    size_t mismatches = 0;
    for (size_t i = 0; i < c.n; ++i) {
      mismatches += gpu_vals[i] != order[i] || gpu_keys[i] != (keys[order[i]] & mask);
    }
    EXPECT_EQ(mismatches, 0u);
  }
}

// --- Whole frames --------------------------------------------------------------------------------

struct Diff {
  float max_rgb = 0, max_alpha = 0, max_depth_rel = 0;
  size_t rgb_beyond = 0, alpha_beyond = 0, depth_beyond = 0, t_beyond = 0, contrib_mismatch = 0;
};

Diff Compare(const RenderOutput& out, const testing::ReferenceImage& ref,
             const vulkan_testing::PixelState& state) {
  Diff d;
  const size_t pixels = static_cast<size_t>(ref.width) * ref.height;
  for (size_t p = 0; p < pixels; ++p) {
    for (int c = 0; c < 3; ++c) {
      const float e = std::abs(out.rgb[p * 3 + c] - ref.rgb[p * 3 + c]);
      d.max_rgb = std::max(d.max_rgb, e);
      d.rgb_beyond += e > 1e-3f;
    }
    const float ea = std::abs(out.alpha[p] - ref.alpha[p]);
    d.max_alpha = std::max(d.max_alpha, ea);
    d.alpha_beyond += ea > 1e-3f;
    const float ed = std::abs(out.depth[p] - ref.depth[p]) / std::max(1.0f, ref.depth[p]);
    d.max_depth_rel = std::max(d.max_depth_rel, ed);
    d.depth_beyond += ed > 1e-3f;
    d.t_beyond += std::abs(state.final_t[p] - ref.final_t[p]) > 1e-3f;
    d.contrib_mismatch += state.n_contrib[p] != ref.n_contrib[p];
  }
  return d;
}

void RenderAndCompare(const GaussianStore& store, const PinholeCamera& camera,
                      const Eigen::Vector3f& background = Eigen::Vector3f(0.1f, 0.2f, 0.3f)) {
  Engine& engine = SharedEngine();
  auto scene = engine.Upload(store);
  ASSERT_TRUE(scene.ok()) << scene.status();
  RenderOptions options;
  options.background = background;
  RenderOutput out;
  ASSERT_TRUE(engine.Render(**scene, camera, options, &out).ok());
  auto state = vulkan_testing::LastPixelState(engine, camera.width, camera.height);
  ASSERT_TRUE(state.ok()) << state.status();
  const testing::ReferenceImage ref = RenderReference(store, camera, background);

  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  ASSERT_EQ(out.width, camera.width);
  ASSERT_EQ(out.height, camera.height);
  ASSERT_EQ(out.rgb.size(), pixels * 3);
  ASSERT_EQ(out.depth.size(), pixels);
  ASSERT_EQ(out.alpha.size(), pixels);
  EXPECT_EQ(out.stats.num_gaussians, store.size());
  // Float projection on two devices: a culling or rect decision may flip at a boundary.
  EXPECT_NEAR(static_cast<double>(out.stats.num_visible), ref.num_visible,
              1 + 0.002 * ref.num_visible);
  EXPECT_NEAR(static_cast<double>(out.stats.num_tile_instances), ref.num_tile_instances,
              2 + 0.002 * ref.num_tile_instances);

  const Diff d = Compare(out, ref, *state);
  if (std::getenv("VK_TEST_VERBOSE")) {
    std::printf(
        "V %zu/%zu I %zu/%zu max rgb %g alpha %g depth %g beyond %zu %zu %zu T %zu nc %zu\n",
        out.stats.num_visible, ref.num_visible, out.stats.num_tile_instances,
        ref.num_tile_instances, d.max_rgb, d.max_alpha, d.max_depth_rel, d.rgb_beyond,
        d.alpha_beyond, d.depth_beyond, d.t_beyond, d.contrib_mismatch);
  }
  const size_t allowed = 2 + pixels / 2000;  // threshold flips (alpha at 1/255, T at 1e-4)
  EXPECT_LE(d.rgb_beyond, allowed) << "max rgb diff " << d.max_rgb;
  EXPECT_LE(d.alpha_beyond, allowed) << "max alpha diff " << d.max_alpha;
  EXPECT_LE(d.depth_beyond, allowed) << "max depth rel diff " << d.max_depth_rel;
  EXPECT_LE(d.t_beyond, allowed);
  EXPECT_LE(d.contrib_mismatch, allowed);
  EXPECT_GE(out.timings.total_ms, 0.0);
  EXPECT_LE(out.timings.projection_ms + out.timings.sort_ms + out.timings.blend_ms,
            out.timings.total_ms + 1e-3);
}

TEST_F(VulkanTest, MatchesReferenceAcrossShDegreesAndSeeds) {
  for (int degree = 0; degree <= 3; ++degree) {
    for (uint32_t seed : {1u, 2u}) {
      SCOPED_TRACE(::testing::Message() << "sh_degree=" << degree << " seed=" << seed);
      SceneOptions opt;
      opt.num_gaussians = 600;
      opt.sh_degree = degree;
      opt.seed = seed + 10 * degree;
      RenderAndCompare(MakeRandomScene(opt), MakeCamera(97, 61, 80.0, 7.5, -4.25));
    }
  }
}

TEST_F(VulkanTest, MatchesReferenceOnKittiSizedFrame) {
  SceneOptions opt;
  opt.num_gaussians = 3000;
  opt.sh_degree = 3;
  opt.seed = 42;
  RenderAndCompare(MakeRandomScene(opt), MakeCamera(1242, 375, 720.0, -30.0, 12.0));
}

// Thin, tilted, semi-transparent splats (the synthetic street): the blend skips, per subgroup,
// the splats whose opacity ellipse misses its pixels; the skip must never drop a contribution.
TEST_F(VulkanTest, MatchesReferenceOnStreetScene) {
  const GaussianStore store =
      MakeSyntheticStreet({.num_gaussians = 20000, .seed = 7, .sh_degree = 1});
  PinholeCamera camera = MakeCamera(621, 188, 360.0, 4.5, -2.5);
  camera.T_world_from_cam = StreetCameraPose(10.0, 0.5);
  RenderAndCompare(store, camera);
}

TEST_F(VulkanTest, MatchesReferenceWithRotatedCameraAndOddSizes) {
  SceneOptions opt;
  opt.num_gaussians = 800;
  opt.sh_degree = 2;
  opt.seed = 5;
  GaussianStore store = MakeRandomScene(opt);
  PinholeCamera cam = MakeCamera(33, 200, 150.0, 3.0, 20.0);
  // Move the scene with the camera so that it stays in view.
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, 1.0, 0.1).normalized()).matrix();
  pose.translation() = Eigen::Vector3d(1.0, -0.5, 2.0);
  cam.T_world_from_cam = pose;
  for (size_t i = 0; i < store.size(); ++i) {
    Eigen::Vector3d p(store.means[i * 3], store.means[i * 3 + 1], store.means[i * 3 + 2]);
    p = pose * p;
    for (int k = 0; k < 3; ++k) store.means[i * 3 + k] = static_cast<float>(p[k]);
  }
  RenderAndCompare(store, cam);
  RenderAndCompare(store, MakeCamera(16, 16, 20.0));
  RenderAndCompare(store, MakeCamera(1, 1, 5.0));
}

TEST_F(VulkanTest, MatchesReferenceWithPairInstances) {
  // Scenes too large for packed (tile << rank_bits | rank) instances use (tile, rank) pairs.
  SceneOptions opt;
  opt.num_gaussians = 1500;
  opt.sh_degree = 1;
  opt.seed = 77;
  vulkan_testing::ForcePairMode(SharedEngine(), true);
  RenderAndCompare(MakeRandomScene(opt), MakeCamera(300, 170, 200.0, 5.0, 3.0));
  vulkan_testing::ForcePairMode(SharedEngine(), false);
}

TEST_F(VulkanTest, EmptySceneIsBackgroundOnly) {
  GaussianStore store;
  store.sh_degree = 1;
  Engine& engine = SharedEngine();
  auto scene = engine.Upload(store);
  ASSERT_TRUE(scene.ok()) << scene.status();
  RenderOptions options;
  options.background = Eigen::Vector3f(0.25f, 0.5f, 1.0f);
  RenderOutput out;
  ASSERT_TRUE(engine.Render(**scene, MakeCamera(40, 30, 50.0), options, &out).ok());
  for (size_t p = 0; p < 40 * 30; ++p) {
    ASSERT_EQ(out.rgb[p * 3 + 0], 0.25f);
    ASSERT_EQ(out.rgb[p * 3 + 1], 0.5f);
    ASSERT_EQ(out.rgb[p * 3 + 2], 1.0f);
    ASSERT_EQ(out.alpha[p], 0.0f);
    ASSERT_EQ(out.depth[p], 0.0f);
  }
  EXPECT_EQ(out.stats.num_gaussians, 0u);
  EXPECT_EQ(out.stats.num_visible, 0u);
  EXPECT_EQ(out.stats.num_tile_instances, 0u);
}

TEST_F(VulkanTest, AllGaussiansCulled) {
  SceneOptions opt;
  opt.num_gaussians = 300;
  GaussianStore store = MakeRandomScene(opt);
  for (size_t i = 0; i < store.size(); ++i)
    store.means[i * 3 + 2] = -std::abs(store.means[i * 3 + 2]) - 0.5f;
  Engine& engine = SharedEngine();
  auto scene = engine.Upload(store);
  ASSERT_TRUE(scene.ok());
  RenderOptions options;
  options.background = Eigen::Vector3f(0.5f, 0.5f, 0.5f);
  options.want_depth = false;
  RenderOutput out;
  ASSERT_TRUE(engine.Render(**scene, MakeCamera(50, 20, 40.0), options, &out).ok());
  EXPECT_EQ(out.stats.num_gaussians, 300u);
  EXPECT_EQ(out.stats.num_visible, 0u);
  EXPECT_EQ(out.stats.num_tile_instances, 0u);
  EXPECT_TRUE(out.depth.empty());
  ASSERT_EQ(out.alpha.size(), 50u * 20u);
  for (float v : out.rgb) ASSERT_EQ(v, 0.5f);
  for (float a : out.alpha) ASSERT_EQ(a, 0.0f);
}

TEST_F(VulkanTest, GrowsInstanceBuffersWhenTheEstimateIsExceeded) {
  // A fresh engine starts from the estimate max(4 N, 16384): 100 huge Gaussians that each cover
  // all 300 tiles need 30000 instances, so the first frame is rendered twice.
  auto created = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
  ASSERT_TRUE(created.ok()) << created.status();
  Engine& engine = **created;
  const int n = 100;
  GaussianStore store;
  store.sh_degree = 0;
  store.Resize(n);
  for (int i = 0; i < n; ++i) {
    store.means[i * 3 + 0] = 0.01f * i;
    store.means[i * 3 + 1] = 0.0f;
    store.means[i * 3 + 2] = 5.0f + i;
    for (int k = 0; k < 3; ++k) store.log_scales[i * 3 + k] = std::log(200.0f);
    store.rotations[i * 4] = 1.0f;
    store.opacity_logits[i] = -3.0f;
    for (int c = 0; c < 3; ++c) store.sh[i * 3 + c] = 0.1f * (c + 1) + 0.01f * i;
  }
  const PinholeCamera camera = MakeCamera(320, 240, 300.0);
  auto scene = engine.Upload(store);
  ASSERT_TRUE(scene.ok()) << scene.status();
  RenderOutput out;
  ASSERT_TRUE(engine.Render(**scene, camera, RenderOptions{}, &out).ok());
  EXPECT_EQ(out.stats.num_tile_instances, 30000u);
  EXPECT_EQ(vulkan_testing::Rerenders(engine), 1);
  EXPECT_GE(vulkan_testing::InstanceCapacity(engine), 30000u);
  const testing::ReferenceImage ref = RenderReference(store, camera, Eigen::Vector3f::Zero());
  float max_diff = 0;
  for (size_t i = 0; i < ref.rgb.size(); ++i) {
    max_diff = std::max(max_diff, std::abs(out.rgb[i] - ref.rgb[i]));
  }
  EXPECT_LT(max_diff, 1e-4f);
  // The next frame starts from the last frame's count: no second render.
  ASSERT_TRUE(engine.Render(**scene, camera, RenderOptions{}, &out).ok());
  EXPECT_EQ(vulkan_testing::Rerenders(engine), 1);
  EXPECT_EQ(vulkan_testing::ValidationMessages(engine), 0);
}

// --- Errors --------------------------------------------------------------------------------------

TEST_F(VulkanTest, RejectsInvalidCameras) {
  Engine& engine = SharedEngine();
  SceneOptions opt;
  opt.num_gaussians = 10;
  auto scene = engine.Upload(MakeRandomScene(opt));
  ASSERT_TRUE(scene.ok());
  RenderOutput out;
  PinholeCamera zero = MakeCamera(10, 10, 10.0);
  zero.width = 0;
  PinholeCamera nan_focal = MakeCamera(10, 10, 10.0);
  nan_focal.fx = std::nan("");
  PinholeCamera too_big = MakeCamera(kMaxImageSide + 1, 10, 10.0);
  PinholeCamera skewed = MakeCamera(10, 10, 10.0);
  skewed.T_world_from_cam.matrix()(0, 1) = 0.5;
  for (const PinholeCamera& cam : {zero, nan_focal, too_big, skewed}) {
    EXPECT_EQ(engine.Render(**scene, cam, RenderOptions{}, &out).code(),
              absl::StatusCode::kInvalidArgument);
  }
}

TEST_F(VulkanTest, RejectsScenesFromElsewhere) {
  class ForeignScene : public DeviceScene {
   public:
    size_t size() const override { return 0; }
    int sh_degree() const override { return 0; }
  } foreign;
  RenderOutput out;
  EXPECT_EQ(SharedEngine().Render(foreign, MakeCamera(8, 8, 8.0), RenderOptions{}, &out).code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(VulkanTest, RejectsTooManyGaussiansAndInvalidStores) {
  GaussianStore huge;
  huge.opacity_logits.resize((size_t{1} << 26) + 1);  // size() is what is checked first
  const absl::Status too_many = SharedEngine().Upload(huge).status();
  EXPECT_EQ(too_many.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(too_many.message(), HasSubstr("2^26"));
  GaussianStore broken = MakeRandomScene(SceneOptions{});
  broken.means.pop_back();
  EXPECT_EQ(SharedEngine().Upload(broken).status().code(), absl::StatusCode::kInvalidArgument);
}

// Training uploads through UpdateSceneParams (param_upload.cc: packed in parallel into one
// persistent staging buffer): the frame must equal a plain Upload's bit for bit at every SH
// degree, in place on the second call, and a non-finite value or a zero rotation anywhere must be
// refused without touching the uploaded scene.
TEST_F(VulkanTest, UpdateSceneParamsRendersLikeUpload) {
  const GaussianStore full = MakeSyntheticStreet({.num_gaussians = 9'001, .seed = 4, .sh_degree = 3});
  PinholeCamera camera = MakeCamera(160, 96, 120.0);
  camera.T_world_from_cam = StreetCameraPose(4.0);
  Engine& engine = SharedEngine();
  for (int degree : {0, 1, 3}) {
    GaussianParamsView v = testing::FullDegreeParamsView(full, degree);
    std::unique_ptr<DeviceScene> updated;
    ASSERT_TRUE(engine.UpdateSceneParams(v, &updated).ok());  // creates the scene
    const DeviceScene* first = updated.get();
    ASSERT_TRUE(engine.UpdateSceneParams(v, &updated).ok());  // in place
    EXPECT_EQ(updated.get(), first);
    const GaussianStore store = testing::TruncatedToDegree(full, degree);
    const int K = store.sh_coeffs();
    auto uploaded = engine.Upload(store);
    ASSERT_TRUE(uploaded.ok());
    RenderOutput a, b;
    ASSERT_TRUE(engine.Render(*updated, camera, {}, &a).ok());
    ASSERT_TRUE(engine.Render(**uploaded, camera, {}, &b).ok());
    EXPECT_GT(a.stats.num_visible, 100u);
    EXPECT_EQ(a.rgb, b.rgb) << "degree " << degree;
    // A nan in the last SH coefficient of the degree, an inf mean, a zero rotation.
    std::vector<float> sh = full.sh, means = full.means, rotations = full.rotations;
    sh[9'000 * 48 + K * 3 - 1] = std::nanf("");
    means[4'321 * 3 + 1] = INFINITY;
    for (int k = 0; k < 4; ++k) rotations[17 * 4 + k] = 0.0f;
    for (int bad = 0; bad < 3; ++bad) {
      GaussianParamsView w = v;
      if (bad == 0) w.sh = sh.data();
      if (bad == 1) w.means = means.data();
      if (bad == 2) w.rotations = rotations.data();
      EXPECT_EQ(engine.UpdateSceneParams(w, &updated).code(), absl::StatusCode::kInvalidArgument) << bad;
    }
    RenderOutput c;
    ASSERT_TRUE(engine.Render(*updated, camera, {}, &c).ok());
    EXPECT_EQ(c.rgb, a.rgb) << "a refused update must leave the scene as it was";
  }
}

}  // namespace
}  // namespace streetsim
