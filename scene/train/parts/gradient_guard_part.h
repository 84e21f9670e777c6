// The gradient guard (gradient_guard.h) as a part: after the camera's and the LiDAR's gradients,
// before the motion prior's and the field's backward, which would spread one Gaussian's nan over
// the whole field.
#pragma once

#include "scene/train/gradient_guard.h"
#include "scene/train/parts/iteration_part.h"

namespace streetsim::train {

class GradientGuardPart : public IterationPart {
 public:
  // More Gaussians than this fraction with a non-finite gradient in one step is divergence, not
  // one degenerate splat.
  static constexpr double kMaxNonFiniteFraction = 0.01;

  absl::StatusOr<double> AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                      ThreadPool& pool) override {
    if (absl::Status s = GuardGradients(i.it, st->size(), kMaxNonFiniteFraction, grads, pool); !s.ok()) return s;
    return 0.0;
  }
};

}  // namespace streetsim::train
