// The cpu backend's copy of a scene: one contiguous array per scalar parameter, so that the
// projection loop reads 16 Gaussians' x (or log-scale, or SH coefficient k of channel c) with one
// vector load instead of gathering through the interleaved store layout.
#pragma once

#include <vector>

#include "absl/status/status.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::cpu {

struct SceneSoa {
  size_t n = 0;
  int sh_degree = 0;
  std::vector<float> mx, my, mz;
  std::vector<float> ls0, ls1, ls2;
  std::vector<float> qw, qx, qy, qz;
  std::vector<float> opacity_logit;
  // Plane (k*3 + c) holds SH coefficient k of channel c for all Gaussians: sh[(k*3+c)*n + i].
  std::vector<float> sh;

  static SceneSoa FromStore(const GaussianStore& store);
  // Training: overwrites this copy from a parameter view in place (vectors keep their capacity),
  // in parallel, checking only what rendering needs: finite values and non-zero rotations.
  // On error the contents are unspecified.
  absl::Status Assign(ThreadPool& pool, const GaussianParamsView& p);
  // Serving: overwrites only `change`'s rows and values (the view must have this copy's size and SH
  // degree), checking them as Assign does. On error the changed rows are unspecified.
  absl::Status AssignRows(ThreadPool& pool, const GaussianParamsView& p, const ParamsChange& change);
};

}  // namespace streetsim::cpu
