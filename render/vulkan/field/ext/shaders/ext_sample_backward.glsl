// Backward of the token features (extended_sampling.h's TokenSampler::Backward + Scatter), shared
// body of ext_sample_backward.comp and its compare-and-swap twin: given dL/dS (the encoder's, or
// none) and dL/df_j for the K tokens, splats dL/d(sample) of the 3 spatial and 3 K space-time
// samples onto their texels (field_plane_grads.glsl: float atomics, any order) and writes
// dL/d(mean) through the sampling coordinates (fixed-order lane sum).
//
// 32 invocations per Gaussian, each taking features lane, lane + 32, ... as
// field_sample_backward.glsl. Per feature: S from the 3 spatial samples; per token, T_j from its 3
// samples, dL/dS += df_j T_j, and the token's samples take dT_j = df_j S times the other two
// (their texel and coordinate gradients right away, so only the spatial samples stay in
// registers); then the spatial samples take dL/dS times the other two; with a dilation, the 12
// dilated samples take dL/dS_dil (binding 13) through their plane means.
#extension GL_GOOGLE_include_directive : require
#include "../../shaders/field_sample_backward_head.glsl"
#include "ext_common.glsl"

layout(std430, binding = 6) readonly buffer DFtok { float d_ftok[]; };  // [rows * K * D]
layout(std430, binding = 12) readonly buffer DS { float d_s[]; };       // [rows * s_stride]
layout(std430, binding = 13) readonly buffer DSDil { float d_sdil[]; };  // [rows * D] (dilation > 0)
#include "../../shaders/field_plane_grads.glsl"

void main() {
  const uint C = CHANNELS;
  const uint D = LEVELS * C;
  const uint K = pc.tokens;
  const uint tid = gl_LocalInvocationID.x;
  const uint lane = tid % LANES;
  const uint g = linear_group_id() * (FIELD_WG / LANES) + tid / LANES;
  float dp[3] = float[3](0.0, 0.0, 0.0);
  if (g < pc.rows) {
    const float p[3] = SampleCoords(g);
    for (uint d = lane; d < D; d += LANES) {
      float dS = pc.s_stride > 0u ? d_s[g * pc.s_stride + pc.s_base + d] : 0.0;
      const float dSd = pc.dilation > 0u ? d_sdil[g * D + d] : 0.0;
      bool any = dS != 0.0 || dSd != 0.0;
      for (uint j = 0u; j < K; ++j) any = any || d_ftok[(g * K + j) * D + d] != 0.0;
      if (!any) continue;  // every dL/d(sample) of this feature is 0
      const uint l = d / C, k = d - l * C;
      const uint R = plane_table[l * PLANES_PER_LEVEL].z;
      const Tap taps[3] = Tap[3](MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R));
      PlaneTaps pts[3];
      float v[3][4];
      float s[3];
      for (uint i = 0u; i < 3u; ++i) {
        const uint c = kSpatialPlanes[i];
        pts[i] = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], taps[PlaneU(c)], taps[PlaneV(c)], C, k);
        s[i] = LoadSample(pts[i], v[i]);
      }
      const float Sv = s[0] * s[1] * s[2];
      for (uint j = 0u; j < K; ++j) {
        const float df = d_ftok[(g * K + j) * D + d];
        const Tap tt = MakeTap(pc.token_time[j], pc.time_res);
        PlaneTaps tp[3];
        float tv[3][4];
        float ts[3];
        for (uint i = 0u; i < 3u; ++i) {
          const uint c = kTimePlanes[i];
          tp[i] = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], taps[PlaneU(c)], tt, C, k);
          ts[i] = LoadSample(tp[i], tv[i]);
        }
        dS += df * (ts[0] * ts[1] * ts[2]);
        const float dT = df * Sv;
        if (dT == 0.0) continue;
        const float gt[3] = float[3](dT * ts[1] * ts[2], dT * ts[0] * ts[2], dT * ts[0] * ts[1]);
        for (uint i = 0u; i < 3u; ++i) {
          const uint cu = PlaneU(kTimePlanes[i]);
          const vec2 duv = SplatSample(tp[i], tv[i], taps[cu].w, tt.w, gt[i]);
          dp[cu] += duv.x * taps[cu].dpx;  // time is not a parameter
        }
      }
      const float gs[3] = float[3](dS * s[1] * s[2], dS * s[0] * s[2], dS * s[0] * s[1]);
      for (uint i = 0u; i < 3u; ++i) {
        const uint c = kSpatialPlanes[i];
        const uint cu = PlaneU(c), cv = PlaneV(c);
        const vec2 duv = SplatSample(pts[i], v[i], taps[cu].w, taps[cv].w, gs[i]);
        dp[cu] += duv.x * taps[cu].dpx;
        dp[cv] += duv.y * taps[cv].dpx;
      }
      if (dSd != 0.0) {
        // S_dil = A_0 A_1 A_2, A_i = ¼ Σ_q s_iq: each tap of plane i takes ¼ dSd times the other
        // two means (internal::TokenSampler's DilatedBackward).
        float A[3];
        for (uint i = 0u; i < 3u; ++i) {
          const uint c = kSpatialPlanes[i];
          const float pu = TexelCoord(p[PlaneU(c)], R), pv = TexelCoord(p[PlaneV(c)], R);
          float a = 0.0;
          for (uint q = 0u; q < 4u; ++q) {
            Tap tu, tv;
            DilatedTaps(pu, pv, R, q, tu, tv);
            float vq[4];
            a += LoadSample(MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], tu, tv, C, k), vq);
          }
          A[i] = 0.25 * a;
        }
        const float dq = dSd * 0.25;
        const float gd[3] = float[3](dq * A[1] * A[2], dq * A[0] * A[2], dq * A[0] * A[1]);
        for (uint i = 0u; i < 3u; ++i) {
          const uint c = kSpatialPlanes[i];
          const uint cu = PlaneU(c), cv = PlaneV(c);
          const float pu = TexelCoord(p[cu], R), pv = TexelCoord(p[cv], R);
          for (uint q = 0u; q < 4u; ++q) {
            Tap tu, tv;
            DilatedTaps(pu, pv, R, q, tu, tv);
            const PlaneTaps pt = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], tu, tv, C, k);
            float vq[4];
            LoadSample(pt, vq);
            const vec2 duv = SplatSample(pt, vq, tu.w, tv.w, gd[i]);
            dp[cu] += duv.x * tu.dpx;
            dp[cv] += duv.y * tv.dpx;
          }
        }
      }
    }
  }
  WriteMeanGrads(tid, lane, g, dp);
}
