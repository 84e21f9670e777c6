// The field's regularisers (spec section 5): second-difference smoothness of the spatial planes
// (plane_tv_weight) and of the space-time planes along time (time_smoothness_weight), and L1 of
// the space-time planes towards 1 (l1_time_planes). The Δ sparsity terms need the deformations and
// live in deformed_scene.h.
#pragma once

#include "render/common/thread_pool.h"
#include "scene/field/field_config.h"

namespace streetsim::field {

struct RegularizerWeights {
  double plane_tv = 1e-4;
  double time_smoothness = 1e-2;
  double l1_time_planes = 1e-4;
};

struct RegularizerLosses {
  double spatial_smoothness = 0;  // sum over levels and spatial planes of S2(P) (unweighted)
  double time_smoothness = 0;     // same over space-time planes
  double l1_time = 0;             // sum over space-time planes of mean |1 - P|
  double weighted = 0;            // the loss added: weights . the three terms
};

// S2(P) = mean over (channel, h in [0, H-3], w) of (P[h+2] - 2 P[h+1] + P[h])^2, along the plane's
// second coordinate (time for space-time planes). Adds the weighted loss's gradient to d_params
// (null: losses only). Each thread writes whole rows of a plane (gather form), so the result does
// not depend on the thread count.
template <typename T>
RegularizerLosses PlaneRegularizers(const FieldLayout& layout, const T* params, const RegularizerWeights& weights,
                                    T* d_params, ThreadPool& pool);

}  // namespace streetsim::field
