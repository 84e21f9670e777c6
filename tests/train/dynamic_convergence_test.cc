// The fine stage on images of a known dynamic scene: a static cloud of Gaussians plus a bright
// cluster that slides 1 m along x over the clip. Each training camera sees the scene at its own
// time (as a car's cameras do); held-out cameras sit between them in angle and time. A static
// model can only blur the cluster over its path; S3Gaussian's field must move it, so its held-out
// PSNR has to come out clearly above the static model's after the same number of iterations.
// The scene, views and options are tests/train/synthetic_scene.h's (shared with
// tests/field/ext_convergence_test.cc).
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>

#include "gtest/gtest.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/field_io.h"
#include "scene/train/trainer.h"
#include "tests/common/scratch_dir.h"
#include "tests/train/synthetic_scene.h"

namespace streetsim::train {
namespace {

using synthetic::MovingClusterOptions;
using synthetic::MovingClusterRun;
using synthetic::MovingClusterViews;

double HeldOutPsnr(FieldMode mode, const std::string& name) {
  const MovingClusterRun scene = MovingClusterViews();
  const TrainOptions opt = MovingClusterOptions(mode);
  const auto dir = std::filesystem::temp_directory_path() / ("streetsim_dynamic_convergence_" + name);
  std::filesystem::remove_all(dir);
  absl::StatusOr<TrainResult> r = TrainOnViews(scene.train, &scene.start, scene.test, dir.string(), opt);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return 0;
  EXPECT_EQ(std::filesystem::exists(dir / "field.bin"), mode == FieldMode::kS3Gaussian);
  std::filesystem::remove_all(dir);
  std::fprintf(stderr, "%s: training PSNR (last 50) %.2f dB, held-out %.2f dB / SSIM %.4f\n", name.c_str(),
               r->train_psnr_mean50, r->heldout.mean.psnr, r->heldout.mean.ssim);
  return r->heldout.mean.psnr;
}

TEST(DynamicConvergence, FieldBeatsTheStaticModelOnAMovingCluster) {
  const double static_psnr = HeldOutPsnr(FieldMode::kStatic, "static");
  const double field_psnr = HeldOutPsnr(FieldMode::kS3Gaussian, "s3gaussian");
  EXPECT_GT(field_psnr, static_psnr + 3.0);
}

// The fine stage with the field on Vulkan (FieldOptions::device kVulkan, forced onto whatever
// Vulkan device exists; lavapipe here) trains like the cpu field: same scene, 60 fine iterations,
// the trained fields and the held-out PSNR agree to float rounding's drift.
TEST(DynamicConvergence, VulkanFieldTrainsLikeTheCpuField) {
  if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device";
  const MovingClusterRun scene = MovingClusterViews();
  std::vector<float> params[2];
  double psnr[2] = {0, 0};
  for (int k = 0; k < 2; ++k) {
    TrainOptions opt = MovingClusterOptions(FieldMode::kS3Gaussian);
    opt.iterations = 160;
    opt.field.device = k == 0 ? FieldDevice::kCpu : FieldDevice::kVulkan;
    const std::string dir = testing::ScratchDir("streetsim_vulkan_field_train", k == 0 ? "cpu" : "vulkan");
    absl::StatusOr<TrainResult> r = TrainOnViews(scene.train, &scene.start, scene.test, dir, opt);
    ASSERT_TRUE(r.ok()) << r.status();
    psnr[k] = r->heldout.mean.psnr;
    absl::StatusOr<field::DeformationField> f = field::LoadField(dir + "/field.bin");
    ASSERT_TRUE(f.ok()) << f.status();
    params[k] = f->params();
  }
  ASSERT_EQ(params[0].size(), params[1].size());
  // Compared with how far training moved the parameters: Adam's normalised steps turn
  // rounding-level differences of near-zero gradients (float atomics on the device) into lr-sized
  // steps, so the two runs drift apart slowly; a wrong gradient would be as large as the movement.
  const TrainOptions ref = MovingClusterOptions(FieldMode::kS3Gaussian);
  absl::StatusOr<field::DeformationField> init = field::DeformationField::Create(
      ref.field.config, AabbOfMeans(scene.start.means), {0, 1}, ref.field.seed + ref.seed);
  ASSERT_TRUE(init.ok()) << init.status();
  double diff = 0, moved = 0;
  for (size_t i = 0; i < params[0].size(); ++i) {
    diff += double(params[0][i] - params[1][i]) * (params[0][i] - params[1][i]);
    moved += double(params[0][i] - init->params()[i]) * (params[0][i] - init->params()[i]);
  }
  std::fprintf(stderr, "field on cpu vs vulkan: |difference| / |training's movement| %.3g, held-out %.2f vs %.2f dB\n",
               std::sqrt(diff / moved), psnr[0], psnr[1]);
  EXPECT_GT(moved, 0.0);
  EXPECT_LT(std::sqrt(diff / moved), 0.05);
  EXPECT_NEAR(psnr[0], psnr[1], 0.2);
}

}  // namespace
}  // namespace streetsim::train
