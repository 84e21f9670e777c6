#pragma once
// A Gaussian whose render gradient is not finite must not end a long run: its gradient row is
// dropped for the step. Many of them mean the run has diverged, which is an error, not something
// to paper over. (What first produced such rows, the projection backward of a Gaussian kilometres
// across, which a field's Δscale can make, is fixed at its cause: render/common/projection_math.h
// ProjectCovariance. The guard stays as the net for anything else.)
#include <cstddef>
#include <cstdint>

#include "absl/status/status.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"

namespace streetsim::train {

struct NonFiniteRows {
  size_t rows = 0;           // Gaussians whose gradient had a non-finite value (now zeroed)
  int64_t first_row = -1;    // the lowest such Gaussian index, -1 if none
};

// Zeroes every per-Gaussian gradient (means, log-scales, rotations, opacity logit, SH, screen mean)
// of each Gaussian that has a non-finite value in any of them. `n` is the Gaussian count.
NonFiniteRows ZeroNonFiniteGradientRows(size_t n, GaussianGrads* grads, ThreadPool& pool);

// ZeroNonFiniteGradientRows, then an error when more than `max_fraction` of the Gaussians were hit
// (the run has diverged: resume from a checkpoint with lower learning rates); logs a warning
// otherwise (the first time, then every 100th iteration that drops rows).
absl::Status GuardGradients(int64_t iteration, size_t n, double max_fraction, GaussianGrads* grads, ThreadPool& pool);

// For a network's flat gradient (the deformation field's planes and MLP, the extension's
// network): an error naming `what` and the iteration when any value is nan or inf, before its
// Adam step would write that into every parameter. Unlike a Gaussian's row nothing can be dropped
// here (every parameter is shared by all Gaussians), so the run stops with its parameters and last
// checkpoint intact.
absl::Status CheckFiniteNetworkGradient(int64_t iteration, const char* what, const float* grad, size_t n,
                                        ThreadPool& pool);

}  // namespace streetsim::train
