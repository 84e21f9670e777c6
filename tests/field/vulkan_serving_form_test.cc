// The serving form's compute kernel (render/vulkan/field/vulkan_serving_form.h) against the host
// form it was made from (ServingForm::At): the values it writes into a Vulkan scene's buffers,
// for S3Gaussian's groups (position and SH, the linear spline) and for every group the extended
// field can move (log-scale, rotation, opacity; the cubic spline, appearance rank 2), with the
// tables split over several buffers; rows the form does not move keep their values; and a
// render of the written scene matches a render of the host form's Gaussians. Skips without a
// Vulkan device.
#include <cmath>
#include <memory>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/engine_impl.h"
#include "render/vulkan/field/vulkan_serving_form.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/serving_form.h"

namespace streetsim::field {
namespace {

constexpr int64_t kStartUs = 1'000'000, kEndUs = 5'000'000;

// A scene whose every third Gaussian stands still and whose others drive, turn, change colour,
// size and opacity smoothly over the log (all_groups: else position and SH only, as S3Gaussian's
// field moves them).
class DriftingScene : public ServedScene {
 public:
  DriftingScene(size_t n, bool all_groups) : all_groups_(all_groups) {
    canonical_.sh_degree = 3;
    canonical_.Resize(n);
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(-1, 1);
    for (size_t i = 0; i < n; ++i) {
      for (int k = 0; k < 3; ++k) canonical_.means[i * 3 + k] = 4 * u(rng) + (k == 2 ? 12.0f : 0.0f);
      for (int k = 0; k < 3; ++k) canonical_.log_scales[i * 3 + k] = -2.5f + 0.3f * u(rng);
      canonical_.rotations[i * 4] = 1;
      canonical_.rotations[i * 4 + 1] = 0.2f * u(rng);
      canonical_.opacity_logits[i] = u(rng);
      if (i % 3 != 0) rows_.push_back(static_cast<uint32_t>(i));
    }
    for (float& s : canonical_.sh) s = 0.3f * u(rng);
    current_ = canonical_;
  }
  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool&) override {
    const double t = std::clamp(double(time_us - kStartUs) / (kEndUs - kStartUs), 0.0, 1.0);
    ++evaluations_;
    for (uint32_t i : rows_) {
      const float phase = 0.37f * static_cast<float>(i);
      const float s = static_cast<float>(std::sin(3 * t + phase)), c = static_cast<float>(std::cos(2 * t + phase));
      current_.means[i * 3 + 0] = canonical_.means[i * 3 + 0] + 8.0f * static_cast<float>(t);  // drives 8 m
      current_.means[i * 3 + 1] = canonical_.means[i * 3 + 1] + 0.3f * s;
      current_.means[i * 3 + 2] = canonical_.means[i * 3 + 2] + 0.05f * c;
      for (int k = 0; k < 48; ++k) current_.sh[i * 48 + k] = canonical_.sh[i * 48 + k] + 0.1f * s * (k % 5 == 0 ? 1 : 0.3f);
      if (!all_groups_) continue;
      for (int k = 0; k < 3; ++k) current_.log_scales[i * 3 + k] = canonical_.log_scales[i * 3 + k] + 0.2f * c;
      current_.rotations[i * 4 + 2] = canonical_.rotations[i * 4 + 2] + 0.3f * s;
      current_.opacity_logits[i] = canonical_.opacity_logits[i] - 0.5f * c;
    }
    return &current_;
  }
  size_t size() const override { return canonical_.size(); }
  size_t num_dynamic() const override { return rows_.size(); }
  int64_t field_evaluations() const override { return evaluations_; }
  FieldTimeRange time_range() const override { return {kStartUs, kEndUs}; }
  int time_cells() const override { return 8; }
  std::vector<uint32_t> dynamic_rows() const override { return rows_; }
  ParamsChange changes() const override { return {}; }

 private:
  bool all_groups_;
  GaussianStore canonical_, current_;
  std::vector<uint32_t> rows_;
  int64_t evaluations_ = 0;
};

struct DeviceValues {
  std::vector<float> geometry;                 // 12 per Gaussian
  std::vector<float> sh;                       // 48 per Gaussian, the store's order
};

DeviceValues Download(Engine& engine, const DeviceScene& scene) {
  auto& ve = dynamic_cast<vulkan::VulkanEngine&>(engine);
  const auto& vs = dynamic_cast<const vulkan::VulkanScene&>(scene);
  const size_t n = scene.size();
  DeviceValues d;
  d.geometry.resize(n * 12);
  EXPECT_TRUE(vulkan::DownloadBytes(ve.context(), vs.gauss, d.geometry.data(), n * 48).ok());
  d.sh.resize(n * 48);
  std::vector<float> group(n * 12);
  for (int g = 0; g < 4; ++g) {
    EXPECT_TRUE(vulkan::DownloadBytes(ve.context(), vs.sh[g], group.data(), n * 48).ok());
    for (size_t i = 0; i < n; ++i)
      for (int k = 0; k < 12; ++k) d.sh[i * 48 + g * 12 + k] = group[i * 12 + k];
  }
  return d;
}

// Every value of every Gaussian within a few ulps of the host form's (the device may fuse a
// multiply-add); returns how many values were compared.
size_t ExpectMatches(const DeviceValues& d, const GaussianStore& h) {
  const size_t n = h.size();
  size_t compared = 0;
  auto near = [&](float dev, float host, size_t i, const char* what) {
    ++compared;
    if (std::abs(dev - host) > 2e-6f * (1.0f + std::abs(host))) {
      ADD_FAILURE() << what << " of Gaussian " << i << ": device " << dev << ", host " << host;
      return false;
    }
    return true;
  };
  for (size_t i = 0; i < n; ++i) {
    const float* g = &d.geometry[i * 12];
    bool ok = true;
    for (int k = 0; k < 3 && ok; ++k) ok = near(g[k], h.means[i * 3 + k], i, "mean");
    ok = ok && near(g[3], h.opacity_logits[i], i, "opacity");
    for (int k = 0; k < 3 && ok; ++k) ok = near(g[4 + k], h.log_scales[i * 3 + k], i, "log-scale");
    for (int k = 0; k < 4 && ok; ++k) ok = near(g[8 + k], h.rotations[i * 4 + k], i, "rotation");
    for (int k = 0; k < 48 && ok; ++k) ok = near(d.sh[i * 48 + k], h.sh[i * 48 + k], i, "SH");
    if (!ok) break;  // one Gaussian's report is enough
  }
  return compared;
}

class VulkanServingFormTest : public ::testing::TestWithParam<bool> {
 protected:
  void SetUp() override {
    absl::StatusOr<std::unique_ptr<Engine>> e = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    if (!e.ok()) GTEST_SKIP() << "no Vulkan device on this machine: " << e.status();
    engine_ = std::move(*e);
  }
  std::unique_ptr<Engine> engine_;
};

TEST_P(VulkanServingFormTest, WritesWhatTheHostFormEvaluatesIntoTheScene) {
  const bool all_groups = GetParam();
  ThreadPool pool(2);
  DriftingScene exact(3000, all_groups);
  // S3Gaussian's groups with the default linear spline; every group with the cubic at rank 2.
  absl::StatusOr<std::unique_ptr<ServingForm>> form =
      all_groups ? ServingForm::Fit(exact, 3, 8, 4, pool, 2) : ServingForm::Fit(exact, 1, 8, 4, pool);
  ASSERT_TRUE(form.ok()) << form.status();
  ASSERT_EQ((*form)->models(FormGroup::kOpacity), all_groups);
  ASSERT_TRUE((*form)->models(FormGroup::kShBands));

  // A scene uploaded at the start, then written by the kernel; tables in buffers of ~100 rows.
  absl::StatusOr<const GaussianStore*> start = (*form)->At(kStartUs, pool);
  ASSERT_TRUE(start.ok());
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = engine_->Upload(**start);
  ASSERT_TRUE(scene.ok()) << scene.status();
  absl::StatusOr<std::unique_ptr<VulkanServingForm>> vk =
      VulkanServingForm::Create(*engine_, **form, /*max_buffer_bytes=*/100 * 4 * 200);
  ASSERT_TRUE(vk.ok()) << vk.status();
  EXPECT_GE((*vk)->table_buffers(), 3);

  // Inside segments, on a knot, before the start and after the end (clamped).
  for (int64_t t : {2'345'678L, 3'000'000L, kStartUs - 500'000, 4'999'000L, kEndUs + 2'000'000, 1'250'000L}) {
    SCOPED_TRACE(t);
    ASSERT_TRUE((*vk)->WriteAt(t, scene->get()).ok());
    absl::StatusOr<const GaussianStore*> host = (*form)->At(t, pool);
    ASSERT_TRUE(host.ok());
    // 59 values per Gaussian: mean, opacity, log-scales, rotation, 48 SH.
    EXPECT_EQ(ExpectMatches(Download(*engine_, **scene), **host), size_t{3000} * 59);
  }
}

TEST_P(VulkanServingFormTest, RendersAsTheHostFormsGaussiansDo) {
  ThreadPool pool(2);
  DriftingScene exact(2000, GetParam());
  absl::StatusOr<std::unique_ptr<ServingForm>> form = ServingForm::Fit(exact, 1, 8, 4, pool);
  ASSERT_TRUE(form.ok()) << form.status();
  absl::StatusOr<std::unique_ptr<DeviceScene>> written = engine_->Upload(**(*form)->At(kStartUs, pool));
  ASSERT_TRUE(written.ok());
  absl::StatusOr<std::unique_ptr<VulkanServingForm>> vk = VulkanServingForm::Create(*engine_, **form);
  ASSERT_TRUE(vk.ok()) << vk.status();
  const int64_t t = 3'700'000;
  ASSERT_TRUE((*vk)->WriteAt(t, written->get()).ok());
  absl::StatusOr<std::unique_ptr<DeviceScene>> uploaded = engine_->Upload(**(*form)->At(t, pool));
  ASSERT_TRUE(uploaded.ok());

  PinholeCamera cam;
  cam.width = 160, cam.height = 120, cam.fx = cam.fy = 120, cam.cx = 80, cam.cy = 60;
  RenderOptions ro;
  RenderOutput a, b;
  ASSERT_TRUE(engine_->Render(**written, cam, ro, &a).ok());
  ASSERT_TRUE(engine_->Render(**uploaded, cam, ro, &b).ok());
  ASSERT_EQ(a.rgb.size(), b.rgb.size());
  double worst = 0, sum = 0;
  for (size_t k = 0; k < a.rgb.size(); ++k) {
    worst = std::max(worst, std::abs(double(a.rgb[k]) - b.rgb[k]));
    sum += b.rgb[k];
  }
  EXPECT_GT(sum, 1.0) << "the camera sees the scene";
  EXPECT_LT(worst, 1e-4);
}

TEST(VulkanServingForm, RefusesAnEngineThatIsNotVulkan) {
  ThreadPool pool(1);
  DriftingScene exact(50, false);
  absl::StatusOr<std::unique_ptr<ServingForm>> form = ServingForm::Fit(exact, 1, 4, 4, pool);
  ASSERT_TRUE(form.ok());
  absl::StatusOr<std::unique_ptr<Engine>> cpu = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(cpu.ok());
  EXPECT_EQ(VulkanServingForm::Create(**cpu, **form).status().code(), absl::StatusCode::kFailedPrecondition);
}

INSTANTIATE_TEST_SUITE_P(Groups, VulkanServingFormTest, ::testing::Bool(),
                         [](const auto& info) { return info.param ? "EveryGroup" : "PositionAndSh"; });

}  // namespace
}  // namespace streetsim::field
