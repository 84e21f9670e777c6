// The extended field's fine stage (--field extended) on the moving-cluster scene of
// tests/train/dynamic_convergence_test.cc (tests/train/synthetic_scene.h): with every
// module on it must train like S3Gaussian's field — held-out PSNR clearly above the static model —
// measured through the scene directory (field.bin + field_ext.bin, LoadSceneField), i.e. with the
// extension at inference.
#include <cstdio>
#include <filesystem>
#include <string>
#include <unistd.h>

#include <Eigen/Geometry>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/trainer.h"
#include "tests/train/synthetic_scene.h"

namespace streetsim::train {
namespace {

using synthetic::MovingClusterOptions;
using synthetic::MovingClusterRun;
using synthetic::MovingClusterViews;

struct RunResult {
  double heldout_dir = 0;      // EvaluateSceneDir: the scene directory as eval reads it
  double heldout_trainer = 0;  // TrainResult::heldout
  double train = 0;            // training PSNR, mean of the last 50 iterations
};

RunResult HeldOut(FieldMode mode, const char* modules, const std::string& name) {
  const MovingClusterRun views = MovingClusterViews();
  const std::vector<View>& test = views.test;
  const TrainOptions opt = MovingClusterOptions(mode, modules);
  const auto dir = std::filesystem::temp_directory_path() /
                   ("streetsim_ext_convergence_" + std::to_string(getpid()) + "_" + name);
  std::filesystem::remove_all(dir);
  RunResult run;
  absl::StatusOr<TrainResult> r = TrainOnViews(views.train, &views.start, test, dir.string(), opt);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return run;
  EXPECT_EQ(std::filesystem::exists(dir / field::kExtendedFieldFileName), modules != nullptr);
  run.heldout_trainer = r->heldout.mean.psnr;
  run.train = r->train_psnr_mean50;
  absl::StatusOr<GaussianStore> scene = ReadGaussianPly((dir / "scene.ply").string());
  EXPECT_TRUE(scene.ok()) << scene.status();
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok());
  if (scene.ok() && engine.ok()) {
    absl::StatusOr<SceneMeta> meta = ReadSceneMeta(dir.string());
    EXPECT_TRUE(meta.ok());
    const Eigen::Vector3f bg(meta->background[0], meta->background[1], meta->background[2]);
    absl::StatusOr<EvalResult> ev = EvaluateSceneDir(**engine, dir.string(), *scene, test, bg);
    EXPECT_TRUE(ev.ok()) << ev.status();
    if (ev.ok()) run.heldout_dir = ev->mean.psnr;
  }
  std::filesystem::remove_all(dir);
  std::fprintf(stderr, "%s: training PSNR (last 50) %.2f dB, held-out %.2f dB (scene directory), %.2f dB (trainer)\n",
               name.c_str(), r->train_psnr_mean50, run.heldout_dir, run.heldout_trainer);
  return run;
}

TEST(ExtendedConvergence, EveryModuleTrainsLikeTheField) {
  const RunResult st = HeldOut(FieldMode::kStatic, nullptr, "static");
  const RunResult ext = HeldOut(FieldMode::kS3Gaussian, "all", "extended_all");
  // The fine stage is chaotic to the last bit (S3Gaussian's own held-out PSNR ranges 36.7-40.4 dB
  // over runs of this scene; the static model 33.0): margins below that spread. Before the gate
  // (extended_config.h) every module on reached 33.2 dB held-out.
  EXPECT_GT(ext.train, st.train + 3.0);
  EXPECT_GT(ext.heldout_dir, st.heldout_dir + 1.5);
}

}  // namespace
}  // namespace streetsim::train
