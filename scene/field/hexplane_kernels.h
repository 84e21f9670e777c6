// Per-Gaussian HexPlane sampling and its backward (internal to scene/field).
//
// grid_sample semantics (align_corners = True, padding_mode = 'border'): the continuous texel
// coordinate px = (p + 1) / 2 * (R - 1) is clamped to [0, R - 1] and interpolated bilinearly; a
// clamped coordinate has zero derivative. Channels are contiguous per texel, so every tap is one
// contiguous run of C values and the channel loops vectorise.
#pragma once

#include <cstddef>
#include <cstdint>

#include "scene/field/field_config.h"

namespace streetsim::field::internal {

template <typename T>
struct Tap {
  int i0 = 0;      // lower texel; the upper one is i0 + 1 (always valid: R >= 2)
  T w = 0;         // weight of the upper texel
  T dpx_dp = 0;    // d(px)/d(p): (R - 1) / 2 inside, 0 where clamped
};

// The tap at the continuous texel coordinate px (MakeTap's rules; the extended field's dilated
// taps shift px by whole texels before the clamp).
template <typename T>
inline Tap<T> MakeTapPx(T px, int resolution) {
  const T rm1 = static_cast<T>(resolution - 1);
  Tap<T> tap;
  tap.dpx_dp = (px > T(0) && px < rm1) ? rm1 * T(0.5) : T(0);
  // Written so that NaN lands on 0 (comparisons with NaN are false): bad input never indexes out.
  px = px > T(0) ? px : T(0);
  px = px < rm1 ? px : rm1;
  int i0 = static_cast<int>(px);
  if (i0 > resolution - 2) i0 = resolution - 2;
  tap.i0 = i0;
  tap.w = px - static_cast<T>(i0);
  return tap;
}

template <typename T>
inline T TexelCoord(T p, int resolution) {
  return (p + T(1)) * T(0.5) * static_cast<T>(resolution - 1);
}

template <typename T>
inline Tap<T> MakeTap(T p, int resolution) {
  return MakeTapPx(TexelCoord(p, resolution), resolution);
}

// The four taps of one plane sample: offset of (u0, v0) relative to the plane and the weights.
template <typename T>
struct PlaneTaps {
  int64_t off00 = 0;
  int64_t row = 0;  // offset from v0 to v1 (width * channels)
  T w00 = 0, w01 = 0, w10 = 0, w11 = 0;
};

template <typename T>
inline PlaneTaps<T> MakePlaneTaps(const Tap<T>& a, const Tap<T>& b, int width, int channels) {
  PlaneTaps<T> t;
  t.row = static_cast<int64_t>(width) * channels;
  t.off00 = static_cast<int64_t>(b.i0) * t.row + static_cast<int64_t>(a.i0) * channels;
  t.w00 = (T(1) - a.w) * (T(1) - b.w);
  t.w01 = a.w * (T(1) - b.w);
  t.w10 = (T(1) - a.w) * b.w;
  t.w11 = a.w * b.w;
  return t;
}

// s[k] = bilinear sample of channel k.
template <typename T>
inline void SamplePlane(const T* __restrict plane, const PlaneTaps<T>& t, int channels, T* __restrict s) {
  const T* __restrict p00 = plane + t.off00;
  const T* __restrict p01 = p00 + channels;
  const T* __restrict p10 = p00 + t.row;
  const T* __restrict p11 = p10 + channels;
  for (int k = 0; k < channels; ++k) s[k] = t.w00 * p00[k] + t.w01 * p01[k] + t.w10 * p10[k] + t.w11 * p11[k];
}

// Multiplies f by the sample (the forward's Hadamard product).
template <typename T>
inline void SampleMulPlane(const T* __restrict plane, const PlaneTaps<T>& t, int channels, T* __restrict f) {
  const T* __restrict p00 = plane + t.off00;
  const T* __restrict p01 = p00 + channels;
  const T* __restrict p10 = p00 + t.row;
  const T* __restrict p11 = p10 + channels;
  for (int k = 0; k < channels; ++k) f[k] *= t.w00 * p00[k] + t.w01 * p01[k] + t.w10 * p10[k] + t.w11 * p11[k];
}

// dL/du and dL/dv of the continuous texel coordinates given dL/ds (g) of one plane sample.
template <typename T>
inline void SampleCoordGrad(const T* __restrict plane, const PlaneTaps<T>& t, T wu, T wv, int channels,
                            const T* __restrict g, T* du, T* dv) {
  const T* __restrict p00 = plane + t.off00;
  const T* __restrict p01 = p00 + channels;
  const T* __restrict p10 = p00 + t.row;
  const T* __restrict p11 = p10 + channels;
  T su = 0, sv = 0;
  for (int k = 0; k < channels; ++k) {
    su += g[k] * ((T(1) - wv) * (p01[k] - p00[k]) + wv * (p11[k] - p10[k]));
    sv += g[k] * ((T(1) - wu) * (p10[k] - p00[k]) + wu * (p11[k] - p01[k]));
  }
  *du = su;
  *dv = sv;
}

// plane += bilinear splat of g (the backward of SamplePlane w.r.t. the plane's texels).
template <typename T>
inline void ScatterPlane(T* __restrict plane, const PlaneTaps<T>& t, int channels, const T* __restrict g) {
  T* __restrict p00 = plane + t.off00;
  T* __restrict p01 = p00 + channels;
  T* __restrict p10 = p00 + t.row;
  T* __restrict p11 = p10 + channels;
  for (int k = 0; k < channels; ++k) {
    const T gk = g[k];
    p00[k] += t.w00 * gk;
    p01[k] += t.w01 * gk;
    p10[k] += t.w10 * gk;
    p11[k] += t.w11 * gk;
  }
}

}  // namespace streetsim::field::internal
