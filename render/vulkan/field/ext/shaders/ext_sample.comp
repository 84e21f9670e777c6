// Token features of the extended field (extended_sampling.h's TokenSampler::Forward): per
// (Gaussian, feature d = level x channel) the spatial product S = s_xy s_xz s_yz once, then for
// each token time t_j the space-time product T_j = s_xt s_yt s_zt and f_j = S T_j, written to
// ftok[g][j * D + d]. S goes to the encoder's input row (with the row's geometry columns copied
// in front of it) when s_stride > 0; with a dilation, S_dil (extended_config.h) to s_dil. One
// invocation per (Gaussian, feature), as field_sample.comp.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "../../shaders/field_common.glsl"
#include "../../shaders/field_planes.glsl"
#include "ext_common.glsl"

layout(local_size_x = 256) in;
layout(std430, binding = 5) readonly buffer Means { float means[]; };  // [rows * 3]
layout(std430, binding = 6) writeonly buffer SOut { float s_out[]; };  // [rows * s_stride]
layout(std430, binding = 7) writeonly buffer Ftok { float ftok[]; };   // [rows * K * D]
layout(std430, binding = 8) readonly buffer Geom { float geom[]; };    // [rows * geom_cols]
layout(std430, binding = 9) writeonly buffer SDil { float s_dil[]; };  // [rows * D] (dilation > 0)

float Sample(uint l, uint c, Tap a, Tap b, uint k) {
  const PlaneTaps pt = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], a, b, CHANNELS, k);
  return pt.w00 * LoadPlane(pt.group, pt.off00) + pt.w01 * LoadPlane(pt.group, pt.off00 + CHANNELS) +
         pt.w10 * LoadPlane(pt.group, pt.off00 + pt.row) + pt.w11 * LoadPlane(pt.group, pt.off00 + pt.row + CHANNELS);
}

void main() {
  const uint C = CHANNELS;
  const uint D = LEVELS * C;
  const uint t = linear_group_id() * FIELD_WG + gl_LocalInvocationID.x;
  if (t >= pc.rows * D) return;
  const uint g = t / D, d = t - g * D;
  const uint l = d / C, k = d - l * C;
  const float p[3] = float[3](pc.ax * means[g * 3u] + pc.bx, pc.ay * means[g * 3u + 1u] + pc.by,
                              pc.az * means[g * 3u + 2u] + pc.bz);
  const uint R = plane_table[l * PLANES_PER_LEVEL].z;
  const Tap taps[3] = Tap[3](MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R));
  float S = 1.0;
  for (uint i = 0u; i < 3u; ++i) {
    const uint c = kSpatialPlanes[i];
    S *= Sample(l, c, taps[PlaneU(c)], taps[PlaneV(c)], k);
  }
  if (pc.s_stride > 0u) {
    s_out[g * pc.s_stride + pc.s_base + d] = S;
    for (uint i = d; i < pc.geom_cols; i += D) s_out[g * pc.s_stride + i] = geom[g * pc.geom_cols + i];
  }
  if (pc.dilation > 0u) {
    // S_dil: per spatial plane the mean of the 4 dilated samples, multiplied over the planes.
    float Sd = 1.0;
    for (uint i = 0u; i < 3u; ++i) {
      const uint c = kSpatialPlanes[i];
      const float pu = TexelCoord(p[PlaneU(c)], R), pv = TexelCoord(p[PlaneV(c)], R);
      float a = 0.0;
      for (uint q = 0u; q < 4u; ++q) {
        Tap tu, tv;
        DilatedTaps(pu, pv, R, q, tu, tv);
        a += Sample(l, c, tu, tv, k);
      }
      Sd *= 0.25 * a;
    }
    s_dil[g * D + d] = Sd;
  }
  for (uint j = 0u; j < pc.tokens; ++j) {
    const Tap tt = MakeTap(pc.token_time[j], pc.time_res);
    float T = 1.0;
    for (uint i = 0u; i < 3u; ++i) {
      const uint c = kTimePlanes[i];
      T *= Sample(l, c, taps[PlaneU(c)], tt, k);
    }
    ftok[(g * pc.tokens + j) * D + d] = S * T;
  }
}
