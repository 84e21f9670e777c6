// The LiDAR step of a training iteration (docs/training.md "LiDAR losses"): the current Gaussians
// are rendered as the training frame's LiDAR sweep (render/lidar, cpu, keep_for_backward) at a
// training column count, compared with the frame's real scan binned to the same range image
// (lidar_losses.h: range L1, return BCE, intensity L1), and the renderer's backward pass gives
// per-Gaussian gradients that are ADDED to the camera step's GaussianGrads before the Adam step.
// Each Gaussian's reflectance is sigmoid(a learned logit) (TrainState::reflectance_logit), stepped
// here by its own Adam; the trained reflectance goes to scene.ply's `reflectance` property.
//
// The sweep is posed as lidar_eval.h poses it: the log's LiDAR mounting, a rolling sweep centred on
// the scan's time stamp over the log's interpolated ego trajectory.
#pragma once

#include <cstdint>
#include <memory>
#include <unordered_map>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "render/lidar/lidar_renderer.h"
#include "scene/log/drive_log.h"
#include "scene/train/lidar_losses.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

// Weights of the three terms (each loss is a mean over rays, lidar_losses.h). The trainer scales
// all three by --lidar-weight.
struct LidarLossWeights {
  float range = 0.1f;       // per metre of mean |range error|
  float ret = 0.05f;        // return / drop BCE
  float intensity = 0.05f;  // mean |intensity error| (reflectance units, [0, 1])
};

// One frame's LiDAR training target: the sensor model at the training column count (mounting
// copied from the log), the sweep pose and the real scan binned into the model's range image.
struct LidarFrameTarget {
  LidarModel model;
  LidarSweepPose sweep;
  int64_t sweep_start_us = 0;
  std::vector<float> range, intensity;  // [beams * columns]; range 0 = no return
};

struct LidarLossTerms {
  double total = 0;  // weighted sum
  double range_l1_m = 0, return_bce = 0, intensity_l1 = 0;  // unweighted
};

// The weighted LiDAR loss of rendered outputs ([beams * columns] each) against a target; ADDS the
// gradients into the three arrays when given (the buffers LidarRenderer::Backward takes).
LidarLossTerms LidarFrameLoss(const float* range_sum, const float* alpha, const float* intensity_sum,
                              const LidarFrameTarget& target, const LidarLossWeights& weights, float* d_range_sum,
                              float* d_alpha, float* d_intensity_sum);

// Renders `store` (the renderer must hold its upload) for the target with reflectance
// sigmoid(reflectance_logit), evaluates LidarFrameLoss and runs the backward pass. grads is
// overwritten: the store's parameters, and grads->reflectance holds dL/d(reflectance LOGIT).
struct LidarGradOptions {
  LidarRenderOptions::Kernel kernel = LidarRenderOptions::Kernel::kSimd;
  bool deterministic = false;
};
absl::StatusOr<LidarLossTerms> LidarFrameLossAndGrads(LidarRenderer& renderer,
                                                      const std::vector<float>& reflectance_logit,
                                                      const LidarFrameTarget& target, const LidarLossWeights& weights,
                                                      const LidarGradOptions& options, LidarGaussianGrads* grads);

// sigmoid of each logit (the reflectance scene.ply carries).
std::vector<float> ReflectanceFromLogits(const std::vector<float>& logits);

struct LidarStageOptions {
  LidarLossWeights weights;
  int columns = 1024;     // training range image width (the eval renders 2048)
  int every = 1;          // LiDAR step on iterations divisible by this
  double reflectance_lr = 0.05;  // Adam lr of the reflectance logits (the opacity logits' lr)
  bool rolling_sweep = true;
  bool deterministic = false;    // the backward's fixed-order reduction
  int num_threads = 0;           // renderer threads (0: STREETSIM_THREADS or all)
};

class LidarStage {
 public:
  // `log` must outlive the stage. InvalidArgument for bad options.
  static absl::StatusOr<std::unique_ptr<LidarStage>> Create(const DriveLog& log, const LidarStageOptions& options);

  // For a training iteration on log frame `frame` whose camera gradients are in `grads` (the
  // state's Gaussians, same size): when due and the frame has a scan, adds the LiDAR gradients
  // into grads (means, log-scales, rotations, opacity logits) and takes an Adam step of the
  // reflectance logits (created at logit 0, i.e. 0.5, when the state has none). Returns the
  // weighted loss (0 when skipped).
  // Fine stage (docs/training.md "Dynamic field"): `render_means` [n*3] are the means the camera
  // rendered, i.e. deformed by the field at the frame's time (used for the whole ~100 ms sweep);
  // the means gradient added is then w.r.t. them, and the caller runs the field's backward
  // (DynamicStage::Backward) on the sum. Null: the state's canonical means. Scales, rotations,
  // opacity and the reflectance logits are canonical either way (the field does not change them).
  absl::StatusOr<double> Step(TrainState* st, int frame, int64_t iteration, GaussianGrads* grads,
                              const std::vector<float>* render_means = nullptr);

  // The frame's target (scan loaded and binned on first use, then cached); nullptr when the frame
  // has no LiDAR observation.
  absl::StatusOr<const LidarFrameTarget*> Target(int frame);

  const LidarStageOptions& options() const { return options_; }
  int64_t steps() const { return steps_; }
  double total_ms() const { return total_ms_; }  // wall time of the steps taken (scan loading excluded)
  const LidarLossTerms& last_terms() const { return last_; }

 private:
  LidarStage(const DriveLog& log, const LidarStageOptions& options);

  const DriveLog* log_;
  LidarStageOptions options_;
  LidarRenderer renderer_;
  std::unordered_map<int, std::unique_ptr<LidarFrameTarget>> targets_;
  GaussianStore geometry_;  // the uploaded copy (no SH)
  LidarGaussianGrads grads_;
  int64_t steps_ = 0;
  double total_ms_ = 0;
  LidarLossTerms last_;
};

}  // namespace streetsim::train
