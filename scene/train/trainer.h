// The static-stage trainer (S3Gaussian's coarse stage, ../shared/docs/s3gaussian-spec.md sections
// 2, 5-7) and held-out evaluation. Data flows one way: DriveLog -> initial scene (scene/init,
// from the training frames only) -> this loop -> scene.ply + checkpoint. The renderer is reached
// only through render/engine.h (Render with keep_for_backward, RenderBackward, UpdateScene).
#pragma once

#include <atomic>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/log/drive_log.h"
#include "scene/train/checkpoint_run.h"
#include "scene/eval/evaluate.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/lidar_stage.h"
#include "scene/train/motion_prior.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

// Low resolution first (resolution_schedule.h): iterations 1..iterations at resolution_scale,
// the rest of the run at TrainOptions::resolution_scale.
struct LowResStage {
  double resolution_scale = 0.25;
  int64_t iterations = 0;
};

struct TrainOptions {
  int iterations = 30000;
  double resolution_scale = 1.0;
  // Low resolution first (LowResStage above). Unset: the whole run at resolution_scale.
  // Train and TrainClip only (TrainOnViews takes views of one resolution).
  std::optional<LowResStage> low_res;
  int holdout_every = 4;
  uint64_t seed = 0;
  bool resume = false;        // continue from out_dir/checkpoint.bin when it exists
  int checkpoint_every = 1000;  // 0: only at the end
  bool sky = true;            // learned background (environment) colour
  bool exposure = false;      // per-image affine colour
  bool depth_loss = true;
  // Learn a pose correction per training view (pose_refinement.h; Hyper's pose_* rates). The run
  // writes DIR/pose_corrections.json and evaluates its held-out views at interpolated corrections.
  bool pose_refinement = false;
  bool deterministic = false;  // fixed-order gradient reduction (identical bits run to run)
  // Stop with Aborted (payload kDivergedAtPayload: the iteration) when the training loss diverges,
  // keeping the last checkpoint from before it (divergence_guard.h).
  bool divergence_guard = true;
  // Grayscale cameras beside colour ones (dataset.h GrayscaleCameras).
  GrayscaleCameras grayscale_cameras = GrayscaleCameras::kLuminance;
  bool write_outputs = true;   // scene.ply, plot, previews at the end
  int stop_after = 0;          // > 0: stop (as if killed) after this iteration, without final outputs
  // Set from outside (the CLI's SIGINT / SIGTERM handler): the run stops after the iteration in
  // progress, writes its checkpoint and returns Cancelled (--resume continues from there).
  const std::atomic<bool>* stop_requested = nullptr;
  Backend backend = Backend::kCpu;
  Hyper hyper;
  double init_voxel_m = 0.15;  // LiDAR init voxel
  // Static only, or S3Gaussian's static + fine stages with the deformation field (iterations is
  // the total; field.static_iterations < iterations). docs/training.md "Dynamic field".
  FieldOptions field;
  // The fine stage's LiDAR motion prior (motion_prior.h; weight 0: off). Built from lidar_log.
  MotionPriorOptions motion_prior;
  // LiDAR losses (lidar_stage.h, docs/training.md "LiDAR losses"): scales the three terms'
  // weights (LidarLossWeights); 0 disables them. Static iterations only; needs lidar_log.
  double lidar_weight = 1.0;
  int lidar_every = 2;       // LiDAR step on every k-th iteration (cost, docs/training.md)
  int lidar_columns = 1024;  // training range image width
  // The log whose scans the LiDAR step reads (Train sets it; TrainOnViews callers may).
  const DriveLog* lidar_log = nullptr;
};

// The payload of a diverged run's Aborted status: the iteration it diverged at, as text.
inline constexpr char kDivergedAtPayload[] = "streetsim.train/diverged_at";

struct Progress {
  int64_t iteration = 0, total = 0;
  double loss = 0, psnr = 0;  // of the last view
  size_t gaussians = 0;
  // Over the last ~100 iterations of the current stage (a fine stage runs at a fraction of the
  // static stage's rate).
  double it_per_s = 0, eta_s = 0;
  // The static stage of a staged run: eta_s is to its end only (the fine stage's rate is not
  // known before it starts).
  bool eta_static_stage_only = false;
  // > 0: the run's low-resolution stage, at this scale; eta_s is to that stage's end at most.
  double low_res_scale = 0;
};

struct TrainResult {
  int64_t iterations = 0;
  size_t gaussians = 0;
  double seconds = 0;
  double seconds_to_psnr24 = -1;
  double train_psnr_mean50 = 0;   // training-view PSNR, mean of the last 50 iterations  // first time a training-view PSNR (running mean of 50) >= 24
  EvalResult heldout;             // when there are held-out views and outputs are written
};

absl::StatusOr<TrainResult> Train(const DriveLog& log, const std::string& out_dir, const TrainOptions& options,
                                  const std::function<void(const Progress&)>& progress = nullptr);

// The initial Gaussians built from the training frames of log.frames[first_frame, end_frame) only
// (held-out frames are never used), with options.init_voxel_m and seed + 1; logs their count.
// Train takes the whole log, a clip of a clip set (clip_training.h) its own frames.
absl::StatusOr<GaussianStore> BuildTrainingInitialScene(const DriveLog& log, int first_frame, int end_frame,
                                                        const TrainOptions& options);

// The same loop on given views and initial Gaussians (what Train does after loading the log and
// building the initial scene; tests use it on rendered images of a known scene). `init` is used
// unless a checkpoint is resumed (may then be null); `heldout` is evaluated at the end (when
// outputs are written). options.holdout_every / resolution_scale only go to train_meta.json.
absl::StatusOr<TrainResult> TrainOnViews(const std::vector<View>& views, const GaussianStore* init,
                                         const std::vector<View>& heldout, const std::string& out_dir,
                                         const TrainOptions& options,
                                         const std::function<void(const Progress&)>& progress = nullptr);

// DIR/train_meta.json written by Train: the background colour and the resolution scale.
struct SceneMeta {
  Eigen::Vector3f background = Eigen::Vector3f::Zero();
  double resolution_scale = 1.0;
  int holdout_every = 4;
  std::string field = "static";  // FieldModeName
  int64_t iterations = 0;         // the iterations the outputs were written at; 0 when not recorded
};
absl::StatusOr<SceneMeta> ReadSceneMeta(const std::string& dir);

}  // namespace streetsim::train
