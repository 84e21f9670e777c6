// The fine stage's LiDAR motion prior (motion_prior.h, docs/training.md "Motion prior") as a
// part: built when the fine stage starts (the log's moving objects tracked once, in the training
// frames' scans only), Gaussians assigned to objects whenever the rows change. Its gradient is
// w.r.t. the field's displacement: added to the rendered means' before the field's backward and
// taken back out of the canonical means' after it (the prior depends on Δx alone).
#pragma once

#include <memory>
#include <vector>

#include "scene/log/drive_log.h"
#include "scene/train/motion_prior.h"
#include "scene/train/parts/iteration_part.h"

namespace streetsim::train {

class MotionPriorPart : public IterationPart {
 public:
  // `lidar_log` (may be null; must outlive the part): the log whose scans are tracked, held-out
  // frames (holdout_every) left out. FailedPrecondition for a prior (weight > 0) without a log.
  static absl::StatusOr<std::unique_ptr<MotionPriorPart>> Create(const MotionPriorOptions& options,
                                                                 const DriveLog* lidar_log, int holdout_every);

  absl::StatusOr<double> AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                      ThreadPool& pool) override;
  void AfterFieldBackward(const Iteration& i, GaussianGrads* grads) override;
  void RowsChanged() override { rows_changed_ = true; }
  void Meta(nlohmann::json* meta) const override;

 private:
  MotionPriorPart(const MotionPriorOptions& options, const DriveLog* lidar_log, int holdout_every)
      : options_(options), lidar_log_(lidar_log), holdout_every_(holdout_every) {}
  // Tracks the objects at the fine stage's first iteration; a preset's prior the log cannot carry
  // is left out with a warning.
  absl::Status Build(const TrainState& st, ThreadPool& pool);

  MotionPriorOptions options_;
  const DriveLog* lidar_log_;
  int holdout_every_;
  std::unique_ptr<MotionPrior> prior_;
  bool skipped_ = false;
  bool rows_changed_ = true;
  std::vector<float> grad_;  // this iteration's dL/dΔx [n*3]
};

}  // namespace streetsim::train
