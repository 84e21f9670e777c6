#include "scene/field/field_regularizers.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace streetsim::field {

namespace {

struct PlaneLoss {
  double s2 = 0, l1 = 0;
};

// One plane; rows [rb, re) of the gradient and the loss terms whose second difference starts at
// a row in [rb, re).
template <typename T>
PlaneLoss PlaneRows(const T* P, T* dP, int H, size_t row_len, bool time_plane, double w_s2, double w_l1, int rb,
                    int re) {
  PlaneLoss out;
  const double n_s2 = static_cast<double>(H - 2) * row_len;
  const double n_l1 = static_cast<double>(H) * row_len;
  const T c_s2 = H >= 3 ? static_cast<T>(2 * w_s2 / n_s2) : T(0);
  const T c_l1 = static_cast<T>(w_l1 / n_l1);
  for (int v = rb; v < re; ++v) {
    const T* r0 = P + v * row_len;
    if (v + 2 < H) {
      const T* r1 = r0 + row_len;
      const T* r2 = r1 + row_len;
      double acc = 0;
      for (size_t i = 0; i < row_len; ++i) {
        const T d = r2[i] - 2 * r1[i] + r0[i];
        acc += static_cast<double>(d) * d;
      }
      out.s2 += acc / n_s2;
    }
    if (time_plane) {
      double acc = 0;
      for (size_t i = 0; i < row_len; ++i) acc += std::abs(static_cast<double>(T(1) - r0[i]));
      out.l1 += acc / n_l1;
    }
    if (!dP) continue;
    // d/dP[v] of sum_h D(h)^2 with D(h) = P[h+2] - 2 P[h+1] + P[h]: D(v-2) - 2 D(v-1) + D(v), each
    // term present only when its h is in [0, H-3]; absent terms read row v with weight 0 (0/1
    // factors keep the loop branch-free so that it vectorises).
    T* g = dP + v * row_len;
    const T f0 = (v - 2 >= 0) ? T(1) : T(0), f1 = (v - 1 >= 0 && v + 1 < H) ? T(1) : T(0),
            f2 = (v + 2 < H) ? T(1) : T(0);
    auto row = [&](int h) { return P + static_cast<size_t>(std::clamp(h, 0, H - 1)) * row_len; };
    const T *a0 = row(v - 2), *a1 = row(v - 1), *a2 = row(v), *a3 = row(v + 1), *a4 = row(v + 2);
    for (size_t i = 0; i < row_len; ++i) {
      const T d0 = a2[i] - 2 * a1[i] + a0[i];
      const T d1 = a3[i] - 2 * a2[i] + a1[i];
      const T d2 = a4[i] - 2 * a3[i] + a2[i];
      g[i] += c_s2 * (f0 * d0 - 2 * f1 * d1 + f2 * d2);
    }
    if (time_plane && c_l1 != T(0)) {
      for (size_t i = 0; i < row_len; ++i) {
        const T x = r0[i] - T(1);
        g[i] += c_l1 * static_cast<T>((x > 0) - (x < 0));
      }
    }
  }
  return out;
}

}  // namespace

template <typename T>
RegularizerLosses PlaneRegularizers(const FieldLayout& L, const T* params, const RegularizerWeights& w, T* d_params,
                                    ThreadPool& pool) {
  RegularizerLosses out;
  constexpr int kRowsPerTask = 16;
  for (const PlaneInfo& p : L.planes) {
    const bool time_plane = PlaneHasTime(p.plane);
    const double w_s2 = time_plane ? w.time_smoothness : w.plane_tv;
    const double w_l1 = time_plane ? w.l1_time_planes : 0;
    const size_t row_len = static_cast<size_t>(p.width) * L.channels;
    const int H = p.height;
    const int tasks = (H + kRowsPerTask - 1) / kRowsPerTask;
    std::vector<PlaneLoss> partial(tasks);
    pool.ParallelFor(tasks, 1, [&](int64_t b, int64_t e, int) {
      for (int64_t t = b; t < e; ++t) {
        const int rb = static_cast<int>(t) * kRowsPerTask;
        const int re = std::min(H, rb + kRowsPerTask);
        partial[t] = PlaneRows(params + p.offset, d_params ? d_params + p.offset : nullptr, H, row_len, time_plane,
                               w_s2, w_l1, rb, re);
      }
    });
    PlaneLoss sum;
    for (const PlaneLoss& q : partial) {
      sum.s2 += q.s2;
      sum.l1 += q.l1;
    }
    if (H < 3) sum.s2 = 0;
    if (time_plane) {
      out.time_smoothness += sum.s2;
      out.l1_time += sum.l1;
    } else {
      out.spatial_smoothness += sum.s2;
    }
  }
  out.weighted = w.plane_tv * out.spatial_smoothness + w.time_smoothness * out.time_smoothness +
                 w.l1_time_planes * out.l1_time;
  return out;
}

template RegularizerLosses PlaneRegularizers<float>(const FieldLayout&, const float*, const RegularizerWeights&,
                                                    float*, ThreadPool&);
template RegularizerLosses PlaneRegularizers<double>(const FieldLayout&, const double*, const RegularizerWeights&,
                                                     double*, ThreadPool&);

}  // namespace streetsim::field
