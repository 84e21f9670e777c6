// Push constants and token taps of the extended field's token sampling (ext_sample.comp,
// ext_sample_backward.glsl; the cpu reference is scene/field/extended/extended_sampling.h).
#ifndef STREETSIM_EXT_COMMON_GLSL_
#define STREETSIM_EXT_COMMON_GLSL_

#define MAX_TOKENS 9u

// p = a * x + b per axis (computed in double on the host, as TokenSampler does); the K token
// times t_j (clamped on the host); S(x) at s_base + g * s_stride + d of `s_out` / `d_s` (the
// encoder's input row [geometry, S]: s_base = geometry columns); dS absent when s_stride = 0.
layout(push_constant, std430) uniform ExtSamplePush {
  float ax, ay, az, bx, by, bz;
  uint rows, time_res, tokens;
  uint s_base, s_stride, geom_cols;
  uint dilation;  // texels of S_dil, the VAE variance branch's input (0: none)
  float token_time[MAX_TOKENS];
} pc;

const uint kSpatialPlanes[3] = uint[3](0u, 1u, 3u);  // xy, xz, yz
const uint kTimePlanes[3] = uint[3](2u, 4u, 5u);     // xt, yt, zt

// Dilated tap q (0..3: u + d, u - d, v + d, v - d) of a plane sample at texel coordinates
// (pu, pv), as internal::DilatedTaps.
void DilatedTaps(float pu, float pv, uint R, uint q, out Tap tu, out Tap tv) {
  const float d = float(pc.dilation) * ((q % 2u) == 0u ? 1.0 : -1.0);
  tu = MakeTapPx(q < 2u ? pu + d : pu, R);
  tv = MakeTapPx(q < 2u ? pv : pv + d, R);
}

#endif  // STREETSIM_EXT_COMMON_GLSL_
