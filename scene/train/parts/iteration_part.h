// The trainer's loop as parts (docs/training.md "How the loop is built"): each concern that adds
// to an iteration's gradient (pose refinement, LiDAR supervision, the gradient guard, the motion
// prior) is an IterationPart, called in a fixed order at fixed points of every iteration. The
// field (field_part.h), the appearance terms (appearance.h) and densification (densification.h)
// sit at their own points with their own small interfaces.
//
// An iteration, in order:
//   field Params -> render -> photometric loss (appearance) -> RenderBackward
//   -> each part's AddGradients (the camera's gradients w.r.t. what was rendered)
//   -> field Backward (gradients become the canonical Gaussians') -> each part's AfterFieldBackward
//   -> densification (RowsChanged to the field and the parts) -> the Gaussians' Adam.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/train/dataset.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

// What a part sees of the iteration in progress.
struct Iteration {
  int64_t it = 0;        // the run's, 1-based
  int64_t stage_it = 0;  // counted from the stage's start (a fine stage counts from its own)
  bool fine = false;     // the field's stage of a field run
  int active_degree = 0;
  int view_index = 0;  // into the training views
  const View* view = nullptr;
  const GaussianParamsView* rendered = nullptr;  // what the camera rendered
  const PinholeCamera* camera = nullptr;         // the camera it rendered with (corrected, when refined)
  // The fine stage: the field's means at the view's time (what was rendered); null otherwise.
  const std::vector<float>* deformed_means = nullptr;
};

class IterationPart {
 public:
  virtual ~IterationPart() = default;
  // After the render's backward, before the field's: adds this concern's gradients to `grads`
  // (the means' are w.r.t. the rendered means; the field chains them) and returns its weighted
  // loss (0 when it has nothing to add this iteration).
  virtual absl::StatusOr<double> AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                              ThreadPool& pool) = 0;
  // After the field's backward (grads are the canonical Gaussians').
  virtual void AfterFieldBackward(const Iteration& i, GaussianGrads* grads) {}
  // The Gaussians' rows changed (densification, the field's reordering).
  virtual void RowsChanged() {}
  // Its entries in train_meta.json (the trained scene's provenance).
  virtual void Meta(nlohmann::json* meta) const {}
  // A line for the end of the run's log (empty: none).
  virtual std::string Summary() const { return {}; }
};

}  // namespace streetsim::train
