// HexPlane features of the extended field (internal): per Gaussian the spatial-plane product S(x)
// (xy, xz, yz; it does not depend on time) and, for each of the K token times t_j, the space-time
// product T(x, t_j) (xt, yt, zt), giving the token features f(x, t_j) = S(x) ⊙ T(x, t_j) per level
// (f(x, t) is S3Gaussian's f). Built on scene/field's per-sample kernels (hexplane_kernels.h:
// taps, bilinear sample, coordinate gradient, splat), so the grid_sample rules are the field's.
//
// With a dilation d > 0 it also gives S_dil(x), the VAE variance branch's input (extended_config.h):
// per level and spatial plane the mean of the 4 samples at texel coordinates (u ± d, v), (u, v ± d),
// multiplied over the 3 planes.
//
// The backward keeps every slot's taps and sample per row of a block (slot = level x {3 spatial,
// 3 x K space-time, 3 x 4 dilated when d > 0}), slot-major (SlotStore); Scatter then splats the
// block's dL/d(sample) one plane per task, in row order (no locks, identical plane gradients for
// any thread count, as FieldBackward does).
#pragma once

#include <algorithm>
#include <vector>

#include "render/common/thread_pool.h"
#include "scene/field/deformation_field.h"
#include "scene/field/hexplane_kernels.h"
#include "scene/field/nn/nn_types.h"

namespace streetsim::field::internal {

inline constexpr int kSpatialPlaneIds[3] = {0, 1, 3};  // xy, xz, yz
inline constexpr int kTimePlaneIds[3] = {2, 4, 5};     // xt, yt, zt
inline constexpr int kMaxSamplerChannels = 256;
inline constexpr int64_t kPrefetchRows = 16;  // sampling: prefetch the taps of the row this far ahead
inline constexpr int kDilatedTaps = 4;        // (u + d, v), (u - d, v), (u, v + d), (u, v - d)

// The backward's kept taps and samples of a block, slot-major: slot s of row r at [s * rows + r]
// (samples: C values each). Each plane's Scatter task then streams its slots' rows as contiguous
// runs; row-major, consecutive rows of one slot sat slots_per_row entries apart, and the scatter
// waited on those loads (field_eval's FieldBackward measured the same, field.md "Speed").
template <typename T>
struct SlotStore {
  PlaneTaps<T>* taps = nullptr;
  T* samples = nullptr;
  size_t rows = 0;  // the whole block's rows: the stride between one slot's entries
  int channels = 0;
  // The store seen from block row `first` (a chunk's rows): row r of the view is row first + r.
  SlotStore from_row(size_t first) const { return {taps + first, samples + first * channels, rows, channels}; }
  PlaneTaps<T>& tap(int slot, int64_t r) const { return taps[static_cast<size_t>(slot) * rows + r]; }
  T* sample(int slot, int64_t r) const { return samples + (static_cast<size_t>(slot) * rows + r) * channels; }
};

// Prefetches the two texel rows (2 texels of C values each) a sample at `pt` reads.
template <typename T>
inline void PrefetchPlaneTaps(const T* plane, const PlaneTaps<T>& pt, int C) {
  const char* a0 = reinterpret_cast<const char*>(plane + pt.off00);
  const char* a1 = reinterpret_cast<const char*>(plane + pt.off00 + pt.row);
  for (size_t o = 0; o < 2 * C * sizeof(T); o += 64) {
    __builtin_prefetch(a0 + o);
    __builtin_prefetch(a1 + o);
  }
}

// The shifted taps of dilated tap q of a plane whose coordinates have texel coordinates pu, pv.
template <typename T>
inline void DilatedTaps(T pu, T pv, int resolution, int dilation, int q, Tap<T>* tu, Tap<T>* tv) {
  const T d = static_cast<T>(q % 2 == 0 ? dilation : -dilation);
  *tu = MakeTapPx(q < 2 ? pu + d : pu, resolution);
  *tv = MakeTapPx(q < 2 ? pv : pv + d, resolution);
}

template <typename T>
class TokenSampler {
 public:
  // Token j's time: clamp(t + (j - (K-1)/2) dt, -1, 1). dilation: texels of S_dil (0: no S_dil).
  TokenSampler(const FieldLayout& L, const T* params, const FieldAabb& aabb, double time_coord, int tokens, double dt,
               int dilation = 0)
      : L_(L), params_(params), K_(tokens), dil_(dilation) {
    for (int k = 0; k < 3; ++k) {
      const double ext = aabb.max[k] - aabb.min[k];
      nm_a[k] = static_cast<T>(-2.0 / ext);
      nm_b[k] = static_cast<T>(1.0 + 2.0 * aabb.min[k] / ext);
    }
    const int kc = (tokens - 1) / 2;
    for (int j = 0; j < tokens; ++j) {
      const double tj = std::clamp(time_coord + (j - kc) * dt, -1.0, 1.0);
      token_time.push_back(static_cast<T>(tokens == 1 ? time_coord : tj));
      time_taps_.push_back(MakeTap(token_time.back(), L.time_resolution));
    }
  }

  int slots_per_level() const { return 3 + 3 * K_ + (dil_ > 0 ? 3 * kDilatedTaps : 0); }
  int dilated_slot(int plane, int q) const { return 3 + 3 * K_ + plane * kDilatedTaps + q; }
  int slots_per_row() const { return L_.num_levels * slots_per_level(); }

  // Rows [b, e) of `means`: S [B, D], Ftok [B, K*D], with a dilation Sdil [B, D] (else untouched).
  // With `keep` (the backward's block storage seen from row b), keeps every slot's taps and
  // sample. Plane-major over the rows with the taps of a row kPrefetchRows ahead prefetched
  // (field_eval's order: the rows' cache misses on a plane overlap).
  // `taps` and `tbuf` are the calling thread's scratch.
  void Forward(const T* means, int64_t b, int64_t e, nn::Mat<T>* S, nn::Mat<T>* Ftok, std::vector<Tap<T>>& taps,
               std::vector<T>& tbuf, const SlotStore<T>* keep, nn::Mat<T>* Sdil = nullptr) const {
    const int C = L_.channels, D = L_.feature_dim(), SL = slots_per_level();
    const int64_t B = e - b;
    S->resize(B, D);
    Ftok->resize(B, static_cast<Eigen::Index>(K_) * D);
    if (dil_ > 0) Sdil->resize(B, D);
    taps.resize(B * 3);
    tbuf.resize(static_cast<size_t>(B) * C);
    // One plane over every row: out[r] *= sample (and keep it for the backward at `slot`).
    auto plane_pass = [&](int l, int c, int j, int slot, T* out, int64_t out_stride) {
      const PlaneInfo& pi = L_.planes[l * kPlanesPerLevel + c];
      const T* plane = params_ + pi.offset;
      const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
      auto tv = [&](int64_t r) -> const Tap<T>& { return cv == 3 ? time_taps_[j] : taps[r * 3 + cv]; };
      for (int64_t r = 0; r < B; ++r) {
        if (r + kPrefetchRows < B) {
          const int64_t q = r + kPrefetchRows;
          PrefetchPlaneTaps(plane, MakePlaneTaps(taps[q * 3 + cu], tv(q), pi.width, C), C);
        }
        const PlaneTaps<T> pt = MakePlaneTaps(taps[r * 3 + cu], tv(r), pi.width, C);
        T* o = out + r * out_stride;
        if (keep) {
          T* smp = keep->sample(slot, r);
          SamplePlane(plane, pt, C, smp);
          for (int k = 0; k < C; ++k) o[k] *= smp[k];
          keep->tap(slot, r) = pt;
        } else {
          SampleMulPlane(plane, pt, C, o);
        }
      }
    };
    for (int l = 0; l < L_.num_levels; ++l) {
      const int R = L_.level_resolution[l];
      for (int64_t r = 0; r < B; ++r)
        for (int k = 0; k < 3; ++k) taps[r * 3 + k] = MakeTap(nm_a[k] * means[(b + r) * 3 + k] + nm_b[k], R);
      S->middleCols(l * C, C).setOnes();
      for (int i = 0; i < 3; ++i) plane_pass(l, kSpatialPlaneIds[i], 0, l * SL + i, S->data() + l * C, D);
      for (int j = 0; j < K_; ++j) {
        std::fill(tbuf.begin(), tbuf.end(), T(1));
        for (int i = 0; i < 3; ++i) plane_pass(l, kTimePlaneIds[i], j, l * SL + 3 + j * 3 + i, tbuf.data(), C);
        for (int64_t r = 0; r < B; ++r) {
          const T* sr = S->row(r).data() + l * C;
          const T* tr = tbuf.data() + r * C;
          T* f = Ftok->row(r).data() + static_cast<size_t>(j) * D + l * C;
          for (int k = 0; k < C; ++k) f[k] = sr[k] * tr[k];
        }
      }
      if (dil_ > 0) DilatedForward(means, b, B, l, Sdil, tbuf, keep);
    }
  }

  // Given dL/dS (rows of stride dS_stride; null = zero) and dL/dFtok [B, K*D]: turns the kept
  // samples into dL/d(sample) in place and adds dL/d(means) through the sampling coordinates.
  // dSdil: dL/dS_dil [B, D] (with a dilation; null = zero).
  // `keep`: the block's storage seen from row b (as Forward kept it).
  void Backward(const T* means, int64_t b, int64_t e, const T* dS, int64_t dS_stride, const T* dFtok,
                const SlotStore<T>& keep, T* d_means, const T* dSdil = nullptr) const {
    const int C = L_.channels, D = L_.feature_dim(), SL = slots_per_level();
    T Sv[kMaxSamplerChannels], dSv[kMaxSamplerChannels], Tv[kMaxSamplerChannels], dT[kMaxSamplerChannels];
    for (int64_t r = 0; r < e - b; ++r) {
      const T* x = means + (b + r) * 3;
      T dp[3] = {0, 0, 0};
      for (int l = 0; l < L_.num_levels; ++l) {
        const int R = L_.level_resolution[l];
        const Tap<T> txyz[3] = {MakeTap(nm_a[0] * x[0] + nm_b[0], R), MakeTap(nm_a[1] * x[1] + nm_b[1], R),
                                MakeTap(nm_a[2] * x[2] + nm_b[2], R)};
        auto ls = [&](int s) { return keep.sample(l * SL + s, r); };  // this level's slot s
        const T* s0 = ls(0);
        const T* s1 = ls(1);
        const T* s2 = ls(2);
        for (int k = 0; k < C; ++k) {
          Sv[k] = s0[k] * s1[k] * s2[k];
          dSv[k] = dS ? dS[r * dS_stride + l * C + k] : T(0);
        }
        // Space-time slots first (they need S), accumulating dL/dS.
        for (int j = 0; j < K_; ++j) {
          T* t0 = ls(3 + j * 3);
          T* t1 = ls(3 + j * 3 + 1);
          T* t2 = ls(3 + j * 3 + 2);
          const T* df = dFtok + r * static_cast<int64_t>(K_) * D + static_cast<int64_t>(j) * D + l * C;
          for (int k = 0; k < C; ++k) {
            Tv[k] = t0[k] * t1[k] * t2[k];
            dSv[k] += df[k] * Tv[k];
            dT[k] = df[k] * Sv[k];
            const T a = t0[k], bb = t1[k], cc = t2[k];
            t0[k] = dT[k] * bb * cc;
            t1[k] = dT[k] * a * cc;
            t2[k] = dT[k] * a * bb;
          }
          for (int i = 0; i < 3; ++i) {
            const int c = kTimePlaneIds[i];
            const int cu = kPlaneCoords[c][0];
            const PlaneInfo& pi = L_.planes[l * kPlanesPerLevel + c];
            T du = 0, dv = 0;
            SampleCoordGrad(params_ + pi.offset, keep.tap(l * SL + 3 + j * 3 + i, r), txyz[cu].w,
                            time_taps_[j].w, C, ls(3 + j * 3 + i), &du, &dv);
            dp[cu] += du * txyz[cu].dpx_dp;  // time is not a parameter
          }
        }
        {
          T* a0 = ls(0);
          T* a1 = ls(1);
          T* a2 = ls(2);
          for (int k = 0; k < C; ++k) {
            const T a = a0[k], bb = a1[k], cc = a2[k];
            a0[k] = dSv[k] * bb * cc;
            a1[k] = dSv[k] * a * cc;
            a2[k] = dSv[k] * a * bb;
          }
        }
        for (int i = 0; i < 3; ++i) {
          const int c = kSpatialPlaneIds[i];
          const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
          const PlaneInfo& pi = L_.planes[l * kPlanesPerLevel + c];
          T du = 0, dv = 0;
          SampleCoordGrad(params_ + pi.offset, keep.tap(l * SL + i, r), txyz[cu].w, txyz[cv].w, C, ls(i), &du,
                          &dv);
          dp[cu] += du * txyz[cu].dpx_dp;
          dp[cv] += dv * txyz[cv].dpx_dp;
        }
        if (dil_ > 0) DilatedBackward(x, l, r, dSdil ? dSdil + r * D + l * C : nullptr, keep, dp);
      }
      if (d_means)
        for (int k = 0; k < 3; ++k) d_means[(b + r) * 3 + k] += dp[k] * nm_a[k];
    }
  }

  // Splats rows [0, bn) of the block's dL/d(sample) into the planes of d_base, one plane per task.
  void Scatter(size_t bn, const SlotStore<T>& keep, T* d_base, ThreadPool& pool) const {
    const int C = L_.channels, SL = slots_per_level();
    const int NP = L_.num_levels * kPlanesPerLevel;
    pool.ParallelFor(NP, 1, [&](int64_t pb, int64_t pe, int) {
      for (int64_t p = pb; p < pe; ++p) {
        const int l = static_cast<int>(p) / kPlanesPerLevel, c = static_cast<int>(p) % kPlanesPerLevel;
        T* grad = d_base + L_.planes[p].offset;
        const bool time = PlaneHasTime(c);
        int idx = 0;
        for (int i = 0; i < 3; ++i)
          if ((time ? kTimePlaneIds[i] : kSpatialPlaneIds[i]) == c) idx = i;
        for (size_t r = 0; r < bn; ++r) {
          for (int j = 0; j < (time ? K_ : 1); ++j) {
            const int slot = l * SL + (time ? 3 + j * 3 + idx : idx);
            ScatterPlane(grad, keep.tap(slot, r), C, keep.sample(slot, r));
          }
          if (dil_ > 0 && !time) {
            for (int q = 0; q < kDilatedTaps; ++q) {
              const int slot = l * SL + dilated_slot(idx, q);
              ScatterPlane(grad, keep.tap(slot, r), C, keep.sample(slot, r));
            }
          }
        }
      }
    });
  }

  T nm_a[3], nm_b[3];
  std::vector<T> token_time;

 private:
  // Level l of S_dil for rows [b, b + B) (the level's columns of Sdil), optionally keeping the
  // 12 dilated slots' taps and samples.
  void DilatedForward(const T* means, int64_t b, int64_t B, int l, nn::Mat<T>* Sdil, std::vector<T>& acc,
                      const SlotStore<T>* keep) const {
    const int C = L_.channels, D = L_.feature_dim(), SL = slots_per_level();
    const int R = L_.level_resolution[l];
    T smp[kMaxSamplerChannels];
    Sdil->middleCols(l * C, C).setOnes();
    for (int i = 0; i < 3; ++i) {
      const int c = kSpatialPlaneIds[i];
      const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
      const PlaneInfo& pi = L_.planes[l * kPlanesPerLevel + c];
      const T* plane = params_ + pi.offset;
      std::fill(acc.begin(), acc.begin() + B * C, T(0));
      auto coords = [&](int64_t r, T* pu, T* pv) {
        *pu = TexelCoord(nm_a[cu] * means[(b + r) * 3 + cu] + nm_b[cu], R);
        *pv = TexelCoord(nm_a[cv] * means[(b + r) * 3 + cv] + nm_b[cv], R);
      };
      for (int64_t r = 0; r < B; ++r) {
        T pu, pv;
        if (r + kPrefetchRows < B) {
          coords(r + kPrefetchRows, &pu, &pv);
          for (int q = 0; q < kDilatedTaps; ++q) {
            Tap<T> tu, tv;
            DilatedTaps(pu, pv, R, dil_, q, &tu, &tv);
            PrefetchPlaneTaps(plane, MakePlaneTaps(tu, tv, pi.width, C), C);
          }
        }
        coords(r, &pu, &pv);
        T* a = acc.data() + r * C;
        for (int q = 0; q < kDilatedTaps; ++q) {
          Tap<T> tu, tv;
          DilatedTaps(pu, pv, R, dil_, q, &tu, &tv);
          const PlaneTaps<T> pt = MakePlaneTaps(tu, tv, pi.width, C);
          T* s = smp;
          if (keep) {
            s = keep->sample(l * SL + dilated_slot(i, q), r);
            keep->tap(l * SL + dilated_slot(i, q), r) = pt;
          }
          SamplePlane(plane, pt, C, s);
          for (int k = 0; k < C; ++k) a[k] += s[k];
        }
      }
      for (int64_t r = 0; r < B; ++r) {
        T* o = Sdil->data() + r * D + l * C;
        const T* a = acc.data() + r * C;
        for (int k = 0; k < C; ++k) o[k] *= T(0.25) * a[k];
      }
    }
  }

  // Level l of row r: the 12 dilated slots' samples -> dL/d(sample) in place given dS_dil (null:
  // zero), dL/d(texel coordinates) added to dp (normalised-coordinate units, like the other slots).
  void DilatedBackward(const T* x, int l, int64_t r, const T* dSd, const SlotStore<T>& keep, T* dp) const {
    const int C = L_.channels, SL = slots_per_level();
    const int R = L_.level_resolution[l];
    T A[3][kMaxSamplerChannels];
    for (int i = 0; i < 3; ++i) {
      for (int k = 0; k < C; ++k) A[i][k] = 0;
      for (int q = 0; q < kDilatedTaps; ++q) {
        const T* s = keep.sample(l * SL + dilated_slot(i, q), r);
        for (int k = 0; k < C; ++k) A[i][k] += s[k];
      }
      for (int k = 0; k < C; ++k) A[i][k] *= T(0.25);
    }
    T g[3][kMaxSamplerChannels];  // dL/d(one tap's sample) of plane i: ¼ dL/dA_i
    for (int k = 0; k < C; ++k) {
      const T d = dSd ? dSd[k] * T(0.25) : T(0);
      g[0][k] = d * A[1][k] * A[2][k];
      g[1][k] = d * A[0][k] * A[2][k];
      g[2][k] = d * A[0][k] * A[1][k];
    }
    for (int i = 0; i < 3; ++i) {
      const int c = kSpatialPlaneIds[i];
      const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
      const PlaneInfo& pi = L_.planes[l * kPlanesPerLevel + c];
      const T pu = TexelCoord(nm_a[cu] * x[cu] + nm_b[cu], R);
      const T pv = TexelCoord(nm_a[cv] * x[cv] + nm_b[cv], R);
      for (int q = 0; q < kDilatedTaps; ++q) {
        T* s = keep.sample(l * SL + dilated_slot(i, q), r);
        for (int k = 0; k < C; ++k) s[k] = g[i][k];
        Tap<T> tu, tv;
        DilatedTaps(pu, pv, R, dil_, q, &tu, &tv);
        T du = 0, dv = 0;
        SampleCoordGrad(params_ + pi.offset, keep.tap(l * SL + dilated_slot(i, q), r), tu.w, tv.w, C, s, &du, &dv);
        dp[cu] += du * tu.dpx_dp;
        dp[cv] += dv * tv.dpx_dp;
      }
    }
  }

  const FieldLayout& L_;
  const T* params_;
  int K_;
  int dil_;
  std::vector<Tap<T>> time_taps_;
};

}  // namespace streetsim::field::internal
