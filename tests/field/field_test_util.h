// Small fields and Gaussians for the field tests.
#pragma once

#include <algorithm>
#include <cmath>
#include <functional>
#include <random>
#include <string>
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

// Standard-normal output gradients dL/dΔx (n * 3) and dL/dΔSH (n * kShOutputs), drawn in that
// order from one generator.
template <typename T>
void RandomOutputGrads(size_t n, uint64_t seed, std::vector<T>* d_dx, std::vector<T>* d_dsh) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<T> g;
  d_dx->resize(n * 3);
  d_dsh->resize(n * kShOutputs);
  for (T& w : *d_dx) w = g(rng);
  for (T& w : *d_dsh) w = g(rng);
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

// The field's parameters by group (planes with / without time, trunk, position head, SH head), for
// per-group gradient errors.
struct Group {
  std::string name;
  std::vector<size_t> index;
};

inline std::vector<Group> ParamGroups(const FieldLayout& L) {
  std::vector<Group> g = {{"spatial planes", {}}, {"time planes", {}}, {"trunk", {}}, {"pos head", {}},
                          {"sh head", {}}};
  for (const PlaneInfo& pi : L.planes) {
    for (size_t i = 0; i < pi.size(L.channels); ++i) g[PlaneHasTime(pi.plane) ? 1 : 0].index.push_back(pi.offset + i);
  }
  auto dense = [&](const DenseInfo& d, int k) {
    for (size_t i = 0; i < static_cast<size_t>(d.out) * d.in; ++i) g[k].index.push_back(d.w_offset + i);
    for (int i = 0; i < d.out; ++i) g[k].index.push_back(d.b_offset + i);
  };
  dense(L.trunk, 2);
  dense(L.pos1, 3);
  dense(L.pos2, 3);
  dense(L.sh1, 4);
  dense(L.sh2, 4);
  return g;
}

// Central difference of f in x[i] with step h; x[i] is restored.
inline double CentralDifference(std::vector<double>& x, size_t i, double h, const std::function<double()>& f) {
  const double x0 = x[i];
  x[i] = x0 + h;
  const double lp = f();
  x[i] = x0 - h;
  const double lm = f();
  x[i] = x0;
  return (lp - lm) / (2 * h);
}

// Relative L2 error of `analytic` against central differences of f over the given entries of x.
// An entry whose estimates at two step sizes disagree (a ReLU or texel-edge kink inside the step)
// is left out; *excluded counts them.
inline double RelError(std::vector<double>& x, const std::vector<size_t>& idx, const std::vector<double>& analytic,
                       const std::function<double()>& f, int* excluded) {
  double num = 0, den = 0;
  *excluded = 0;
  for (size_t i : idx) {
    const double h = 1e-6 * std::max(1.0, std::abs(x[i]));
    const double fd1 = CentralDifference(x, i, h, f), fd2 = CentralDifference(x, i, 2 * h, f);
    if (std::abs(fd1 - fd2) > 1e-5 * std::max(1e-3, std::abs(fd1))) {
      ++*excluded;
      continue;
    }
    num += (analytic[i] - fd1) * (analytic[i] - fd1);
    den += fd1 * fd1;
  }
  return den > 0 ? std::sqrt(num / den) : std::sqrt(num);
}

// The finest xt plane made to vary in time over its 2 * half_width middle texel columns (the
// others stay at the spec's 1): the field then moves the Gaussians in that band of x and leaves
// the rest still (static skip, decomposition and served-scene tests).
inline void AddTimeVaryingBand(DeformationField* f, int half_width) {
  const FieldLayout& L = f->layout();
  for (const PlaneInfo& pi : L.planes) {
    if (pi.plane != 2 || pi.level != L.num_levels - 1) continue;
    for (int v = 0; v < pi.height; ++v)
      for (int u = pi.width / 2 - half_width; u < pi.width / 2 + half_width; ++u)
        for (int k = 0; k < L.channels; ++k)
          f->mutable_params()[pi.offset + (size_t(v) * pi.width + u) * L.channels + k] = 1.0f + 0.8f * std::sin(2.0f * v + k);
  }
}

}  // namespace streetsim::field::testing
