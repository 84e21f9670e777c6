// The fine stage on images of a known dynamic scene: a static cloud of Gaussians plus a bright
// cluster that slides 1 m along x over the clip. Each training camera sees the scene at its own
// time (as a car's cameras do); held-out cameras sit between them in angle and time. A static
// model can only blur the cluster over its path; S3Gaussian's field must move it, so its held-out
// PSNR has to come out clearly above the static model's after the same number of iterations.
// The scene, views and options are tests/train/synthetic_scene.h's (shared with
// tests/field/ext_convergence_test.cc).
#include <cstdio>
#include <filesystem>
#include <string>

#include "gtest/gtest.h"
#include "scene/train/trainer.h"
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

}  // namespace
}  // namespace streetsim::train
