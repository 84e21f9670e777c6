#include "scene/train/trainer.h"

#include <filesystem>
#include <fstream>
#include <optional>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/init/initial_scene.h"
#include "scene/train/dynamic_pixels.h"
#include "scene/train/resolution_schedule.h"
#include "scene/train/train_loop.h"

namespace streetsim::train {
namespace {

absl::Status CheckFieldOptions(const TrainOptions& opt) {
  if (opt.field.mode != FieldMode::kS3Gaussian) return absl::OkStatus();
  if (opt.field.static_iterations < 0 || opt.field.static_iterations >= opt.iterations) {
    return absl::InvalidArgumentError(absl::StrCat("--static-iterations must be in 0..", opt.iterations - 1,
                                                   " (below --iterations, the total), not ",
                                                   opt.field.static_iterations));
  }
  return opt.field.config.Validate();
}

}  // namespace

absl::StatusOr<SceneMeta> ReadSceneMeta(const std::string& dir) {
  SceneMeta meta;
  const std::string path = (std::filesystem::path(dir) / "train_meta.json").string();
  std::ifstream f(path);
  if (!f) return meta;  // a scene.ply from elsewhere: black background, scale 1
  try {
    const nlohmann::json j = nlohmann::json::parse(f);
    for (int c = 0; c < 3; ++c) meta.background[c] = j.at("background").at(c).get<float>();
    meta.resolution_scale = j.at("resolution_scale").get<double>();
    meta.holdout_every = j.at("holdout_every").get<int>();
    meta.field = j.value("field", std::string("static"));
    meta.iterations = j.value("iterations", int64_t{0});
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
  return meta;
}

absl::StatusOr<GaussianStore> BuildTrainingInitialScene(const DriveLog& log, int first_frame, int end_frame,
                                                        const TrainOptions& opt) {
  const DriveLog train_log = TrainingFramesLog(log, first_frame, end_frame, opt.holdout_every);
  InitOptions iopt;
  iopt.voxel_m = opt.init_voxel_m;
  iopt.seed = static_cast<unsigned>(opt.seed + 1);
  InitStats istats;
  absl::StatusOr<GaussianStore> built = BuildInitialScene(train_log, iopt, &istats);
  if (!built.ok()) return built.status();
  LOG(INFO) << "initial scene: " << built->size() << " Gaussians (" << istats.source << ")";
  for (const std::string& note : istats.notes) LOG(INFO) << "initial scene: " << note;
  return built;
}

namespace {

// Train at one resolution (opt.resolution_scale); Train runs it once per resolution stage.
absl::StatusOr<TrainResult> TrainLogAtScale(const DriveLog& log, const std::string& out_dir, const TrainOptions& opt,
                                            const std::function<void(const Progress&)>& progress) {
  if (opt.iterations < 1) return absl::InvalidArgumentError("iterations must be >= 1");
  if (absl::Status s = CheckFieldOptions(opt); !s.ok()) return s;
  DatasetOptions dopt;
  dopt.grayscale = opt.grayscale_cameras;
  dopt.resolution_scale = opt.resolution_scale;
  dopt.holdout_every = opt.holdout_every;
  dopt.split = Split::kTrain;
  dopt.load_depth = opt.depth_loss;
  absl::StatusOr<std::vector<View>> views = LoadViews(log, dopt);
  if (!views.ok()) return views.status();
  if (views->empty()) return absl::InvalidArgumentError("the log has no training views");
  std::vector<View> test;
  if (opt.write_outputs && opt.holdout_every > 0) {
    dopt.split = Split::kTest;
    dopt.load_depth = true;
    absl::StatusOr<std::vector<View>> t = LoadViews(log, dopt);
    if (!t.ok()) return t.status();
    test = std::move(*t);
    // PSNR* of the held-out views (the masks read scans only, never trained on).
    if (absl::Status s = AttachDynamicPixels(log, &test); !s.ok()) return s;
  }
  TrainOptions topt = opt;
  if (topt.field.mode == FieldMode::kS3Gaussian && topt.field.time_range.start_us == 0 &&
      topt.field.time_range.end_us == 0 && !log.frames.empty()) {
    // The field's time axis spans the whole log, held-out frames included.
    topt.field.time_range = {log.frames.front().time_us, log.frames.back().time_us};
  }
  const std::string ckpt_path = (std::filesystem::path(out_dir) / "checkpoint.bin").string();
  std::optional<GaussianStore> init;
  if (!(opt.resume && std::filesystem::exists(ckpt_path))) {
    // The initial scene sees the training frames only: held-out frames are never used.
    absl::StatusOr<GaussianStore> built =
        BuildTrainingInitialScene(log, 0, static_cast<int>(log.frames.size()), opt);
    if (!built.ok()) return built.status();
    init = std::move(*built);
  }
  if (topt.lidar_log == nullptr) topt.lidar_log = &log;
  return TrainOnViews(*views, init ? &*init : nullptr, test, out_dir, topt, progress);
}

}  // namespace

absl::StatusOr<TrainResult> Train(const DriveLog& log, const std::string& out_dir, const TrainOptions& opt,
                                  const std::function<void(const Progress&)>& progress) {
  return TrainInResolutionStages(
      opt, out_dir, progress,
      [&](const TrainOptions& stage, const std::function<void(const Progress&)>& stage_progress) {
        return TrainLogAtScale(log, out_dir, stage, stage_progress);
      });
}

absl::StatusOr<TrainResult> TrainOnViews(const std::vector<View>& train_views, const GaussianStore* init,
                                         const std::vector<View>& heldout, const std::string& out_dir,
                                         const TrainOptions& opt,
                                         const std::function<void(const Progress&)>& progress) {
  if (opt.iterations < 1) return absl::InvalidArgumentError("iterations must be >= 1");
  if (train_views.empty()) return absl::InvalidArgumentError("no training views");
  if (absl::Status s = CheckFieldOptions(opt); !s.ok()) return s;
  TrainLoop loop(train_views, heldout, out_dir, opt, progress);
  if (absl::Status s = loop.Setup(init); !s.ok()) return s;
  return loop.Run();
}

}  // namespace streetsim::train
