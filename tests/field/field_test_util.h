// Small fields and Gaussians for the field tests.
#pragma once

#include <random>
#include <vector>

#include "scene/field/deformation_field.h"
#include "scene/field/field_config.h"
#include "scene/field/field_eval.h"

namespace streetsim::field::testing {

// 2 levels, 4 channels, spatial 4 / 8, time 5, width 8: every parameter can be finite-differenced.
inline FieldConfig SmallConfig() {
  FieldConfig c;
  c.channels = 4;
  c.base_resolution = 4;
  c.multires = {1, 2};
  c.time_resolution = 5;
  c.width = 8;
  return c;
}

inline FieldAabb TestAabb() {
  FieldAabb a;
  a.min[0] = -3; a.min[1] = -2; a.min[2] = -1;
  a.max[0] = 5;  a.max[1] = 4;  a.max[2] = 1.5;
  return a;
}

inline FieldQuery TestQuery(double time_coord) {
  FieldQuery q;
  const FieldAabb a = TestAabb();
  for (int k = 0; k < 3; ++k) {
    q.aabb_min[k] = a.min[k];
    q.aabb_max[k] = a.max[k];
  }
  q.time_coord = time_coord;
  return q;
}

// Spec init, then time planes moved off 1 so that the output depends on time.
template <typename T>
std::vector<T> RandomParams(const FieldConfig& c, const FieldLayout& L, uint64_t seed) {
  std::vector<T> p;
  InitFieldParams(c, L, seed, &p);
  std::mt19937_64 rng(seed + 1);
  std::uniform_real_distribution<double> u(-0.3, 0.3);
  for (const PlaneInfo& pi : L.planes) {
    if (!PlaneHasTime(pi.plane)) continue;
    for (size_t i = 0; i < pi.size(L.channels); ++i) p[pi.offset + i] += static_cast<T>(u(rng));
  }
  return p;
}

// n positions in the test AABB, `outside` of them beyond it (border clamp).
template <typename T>
std::vector<T> RandomMeans(size_t n, size_t outside, uint64_t seed) {
  std::mt19937_64 rng(seed);
  const FieldAabb a = TestAabb();
  std::vector<T> m(n * 3);
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      const double ext = a.max[k] - a.min[k];
      std::uniform_real_distribution<double> u(a.min[k] + 0.01 * ext, a.max[k] - 0.01 * ext);
      m[i * 3 + k] = static_cast<T>(u(rng));
    }
    if (i < outside) m[i * 3 + i % 3] = static_cast<T>(a.max[i % 3] + 0.7);
  }
  return m;
}

}  // namespace streetsim::field::testing
