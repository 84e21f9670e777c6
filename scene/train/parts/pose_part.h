// Camera pose refinement (pose_refinement.h, docs/training.md "Camera pose refinement") as a part:
// a learned correction per training view, applied to the camera before the render, stepped from
// the camera's gradient alone (before the LiDAR's joins the means') between the schedule's
// iterations, written as DIR/pose_corrections.json at the end; held-out views are then evaluated
// at interpolated corrections.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "scene/train/parts/iteration_part.h"

namespace streetsim::train {

class PosePart : public IterationPart {
 public:
  // `asked`: the run refines its poses. A checkpoint that refines its poses goes on refining them:
  // its scene sits in the corrected trajectory's frame, and the log's poses would misplace every
  // view of it. FailedPrecondition when the checkpoint has corrections for another view count.
  static absl::StatusOr<std::unique_ptr<PosePart>> Create(bool asked, int num_views, const Hyper& h, TrainState* st);

  bool refining() const { return refining_; }
  // The camera a training view renders with.
  PinholeCamera Camera(const View& view, int view_index, const TrainState& st) const;

  absl::StatusOr<double> AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                      ThreadPool& pool) override;

  // At the run's end: writes (or, not refining, removes) DIR/pose_corrections.json and returns the
  // held-out views as evaluation renders them, with their interpolated corrections (nullopt: as
  // they are).
  absl::StatusOr<std::optional<std::vector<View>>> Finish(const std::string& out_dir,
                                                          const std::vector<View>& train_views, const TrainState& st,
                                                          const std::vector<View>& heldout) const;

 private:
  PosePart(bool refining, const Hyper& h) : refining_(refining), h_(h) {}
  bool refining_;
  Hyper h_;
};

}  // namespace streetsim::train
