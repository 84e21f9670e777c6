// Densification (../shared/docs/s3gaussian-spec.md section 7, train_state.h DensifyAndPrune): the
// view-space gradient statistics, clone / split / prune every densify_interval iterations and the
// opacity reset, counted in iterations of the stage, up to densify_until. The trainer passes on
// what it did: changed rows to the field and the parts, a reset to the divergence guard.
#pragma once

#include <cstdint>

#include "scene/train/train_state.h"

namespace streetsim::train {

struct DensifyEvents {
  bool rows_changed = false;   // cloned, split or pruned (new rows, new order)
  bool opacity_reset = false;  // every opacity lowered: the loss jumps on purpose
  // The Gaussian tensors were replaced this iteration: 3DGS's Adam sees no gradient for them.
  bool replaced() const { return rows_changed || opacity_reset; }
};

class Densification {
 public:
  // `iterations`: the run's last; `outputs_at_end`: the run writes its scene there (no reset then
  // within Hyper::min_iterations_after_reset of it).
  Densification(const Hyper& h, int64_t iterations, bool outputs_at_end)
      : h_(h), iterations_(iterations), outputs_at_end_(outputs_at_end) {}

  // After the iteration's gradients are final (canonical), before the Gaussians' Adam.
  DensifyEvents Step(int64_t it, int64_t stage_it, const GaussianGrads& grads, int width, int height,
                     TrainState* st) const;

 private:
  Hyper h_;
  int64_t iterations_;
  bool outputs_at_end_;
};

}  // namespace streetsim::train
