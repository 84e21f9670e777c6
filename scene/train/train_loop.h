// One training run on given views (TrainOnViews, trainer.h): the state loaded or initialised, the
// loop's parts assembled from the options (parts/iteration_part.h), the iterations run, the
// checkpoints and the divergence guard kept, and the run's outputs written at the end.
#pragma once

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/train/dataset.h"
#include "scene/train/divergence_guard.h"
#include "scene/train/parts/appearance.h"
#include "scene/train/parts/densification.h"
#include "scene/train/parts/field_part.h"
#include "scene/train/parts/iteration_part.h"
#include "scene/train/parts/pose_part.h"
#include "scene/train/train_state.h"
#include "scene/train/trainer.h"

namespace streetsim::train {

class TrainLoop {
 public:
  // The views, options and callback must outlive the loop.
  TrainLoop(const std::vector<View>& views, const std::vector<View>& heldout, const std::string& out_dir,
            const TrainOptions& options, const std::function<void(const Progress&)>& progress);

  // The state (a checkpoint's, or `init`'s: may be null on a resume) and the parts.
  absl::Status Setup(const GaussianStore* init);
  // The iterations to the end (or to a stop, a divergence) and the outputs.
  absl::StatusOr<TrainResult> Run();

 private:
  using Clock = std::chrono::steady_clock;
  absl::Status LoadOrInitState(const GaussianStore* init);
  absl::Status AssembleParts();
  // One iteration; its loss, and the training view's PSNR in *psnr.
  absl::StatusOr<double> Iterate(int64_t it, double* psnr);
  // L1 + D-SSIM (+ depth) of `image` against the view's, gradients into d_rgb_ / d_depth_.
  double PhotometricLoss(const View& view, const std::vector<float>& gt, const std::vector<float>& image,
                         double* psnr);
  absl::Status SaveCheckpoint();
  void LogSummaries(bool run_end) const;
  absl::Status WriteOutputs();
  absl::Status EvaluateHeldOut(const std::vector<View>& test);

  const std::vector<View>& views_;
  const std::vector<View>& heldout_;
  const std::string out_dir_, ckpt_path_;
  const TrainOptions& opt_;
  const std::function<void(const Progress&)>& progress_;
  const Clock::time_point t_start_ = Clock::now();

  TrainState st_;
  std::unique_ptr<Engine> engine_;
  ThreadPool pool_{0};
  std::unique_ptr<DeviceScene> scene_;
  RenderOutput out_;
  GaussianGrads grads_;
  std::vector<float> d_rgb_, d_depth_, luma_, d_luma_;
  std::vector<std::vector<float>> gt_cache_;

  Appearance appearance_;
  std::unique_ptr<PosePart> poses_;
  std::unique_ptr<FieldPart> field_;
  const Densification densification_;
  // In the order they run: pose refinement (the camera's gradient alone), LiDAR, the gradient
  // guard, the motion prior.
  std::vector<std::unique_ptr<IterationPart>> owned_parts_;
  std::vector<IterationPart*> parts_;

  // The loss watched for divergence (divergence_guard.h); the fine stage's start and opacity
  // resets move it on purpose.
  DivergenceGuard guard_;
  int64_t saved_iteration_ = -1;  // the last checkpoint's, so that a stop right after one is free
  TrainResult result_;
};

}  // namespace streetsim::train
