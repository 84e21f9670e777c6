// Backward of the HexPlane features (shared body of field_sample_backward.comp and its
// compare-and-swap twin): given dL/dF, the plane-texel gradients (bilinear splat, added with float
// atomics) and dL/d(canonical mean) through the sampling coordinates (zero where clamped), as
// field_eval.cc's FeatureRowBackward + ScatterPlane.
//
// 32 invocations per Gaussian (8 per workgroup; nothing assumes a subgroup size): invocation
// `lane` takes features lane, lane + 32, ... (neighbouring lanes: neighbouring channels of the same
// texels). Per feature it re-samples the level's 6 planes, forms dL/d(sample) with prefix/suffix
// products (no division: a sample can be 0), splats it onto the 4 texels of each plane and adds
// its share of the coordinate gradient; the 32 shares are summed in shared memory (fixed order:
// d_means is deterministic, the plane gradients are not, their atomics land in any order).
#extension GL_GOOGLE_include_directive : require
#ifndef CAS_ATOMICS
#extension GL_EXT_shader_atomic_float : require
#endif
#include "field_common.glsl"
#include "field_planes.glsl"

#define LANES 32u

layout(local_size_x = 256) in;
layout(std430, binding = 5) readonly buffer Means { float means[]; };       // [rows * 3]
layout(std430, binding = 6) readonly buffer DFeatures { float d_features[]; };  // [rows * D]
layout(std430, binding = 7) writeonly buffer DMeans { float d_means[]; };   // [rows * 3]
#ifdef CAS_ATOMICS
#define GRAD_T uint
#else
#define GRAD_T float
#endif
// Plane gradients, grouped as the planes (binding 8 + group).
layout(std430, binding = 8) buffer Grads0 { GRAD_T grads0[]; };
layout(std430, binding = 9) buffer Grads1 { GRAD_T grads1[]; };
layout(std430, binding = 10) buffer Grads2 { GRAD_T grads2[]; };
layout(std430, binding = 11) buffer Grads3 { GRAD_T grads3[]; };
SAMPLE_PUSH

#ifdef CAS_ATOMICS
#define ATOMIC_ADD_F(buf, i, v)                                                               \
  {                                                                                           \
    uint old_ = buf[i];                                                                       \
    for (;;) {                                                                                \
      const uint prev_ = atomicCompSwap(buf[i], old_, floatBitsToUint(uintBitsToFloat(old_) + (v))); \
      if (prev_ == old_) break;                                                               \
      old_ = prev_;                                                                           \
    }                                                                                         \
  }
#else
#define ATOMIC_ADD_F(buf, i, v) atomicAdd(buf[i], (v))
#endif

void AddGrad(uint group, uint i, float v) {
  if (v == 0.0) return;  // border taps (weight 0) and zero gradients: adding 0 changes nothing
  switch (group) {
    case 0u: ATOMIC_ADD_F(grads0, i, v); break;
    case 1u: ATOMIC_ADD_F(grads1, i, v); break;
    case 2u: ATOMIC_ADD_F(grads2, i, v); break;
    default: ATOMIC_ADD_F(grads3, i, v); break;
  }
}

shared float red[3][256];

void main() {
  const uint C = CHANNELS;
  const uint D = LEVELS * C;
  const uint tid = gl_LocalInvocationID.x;
  const uint lane = tid % LANES;
  const uint g = linear_group_id() * (FIELD_WG / LANES) + tid / LANES;
  float dp[3] = float[3](0.0, 0.0, 0.0);
  if (g < pc.rows) {
    const float p[3] = float[3](pc.ax * means[g * 3u] + pc.bx, pc.ay * means[g * 3u + 1u] + pc.by,
                                pc.az * means[g * 3u + 2u] + pc.bz);
    const Tap tt = MakeTap(pc.time_coord, pc.time_res);
    for (uint d = lane; d < D; d += LANES) {
      const float df = d_features[g * D + d];
      if (df == 0.0) continue;  // every dL/d(sample) of this feature is 0
      const uint l = d / C, k = d - l * C;
      const uint R = plane_table[l * PLANES_PER_LEVEL].z;
      const Tap taps[4] = Tap[4](MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R), tt);
      PlaneTaps pts[6];
      float v[6][4];
      float s[6];
      for (uint c = 0u; c < PLANES_PER_LEVEL; ++c) {
        pts[c] = MakePlaneTaps(plane_table[l * PLANES_PER_LEVEL + c], taps[PlaneU(c)], taps[PlaneV(c)], C, k);
        v[c][0] = LoadPlane(pts[c].group, pts[c].off00);
        v[c][1] = LoadPlane(pts[c].group, pts[c].off00 + C);
        v[c][2] = LoadPlane(pts[c].group, pts[c].off00 + pts[c].row);
        v[c][3] = LoadPlane(pts[c].group, pts[c].off00 + pts[c].row + C);
        s[c] = pts[c].w00 * v[c][0] + pts[c].w01 * v[c][1] + pts[c].w10 * v[c][2] + pts[c].w11 * v[c][3];
      }
      float suf[6];
      suf[5] = 1.0;
      for (int c = 4; c >= 0; --c) suf[c] = suf[c + 1] * s[c + 1];
      float pre = df;
      for (uint c = 0u; c < PLANES_PER_LEVEL; ++c) {
        const float gc = pre * suf[c];
        pre *= s[c];
        const PlaneTaps pt = pts[c];
        AddGrad(pt.group, pt.off00, pt.w00 * gc);
        AddGrad(pt.group, pt.off00 + C, pt.w01 * gc);
        AddGrad(pt.group, pt.off00 + pt.row, pt.w10 * gc);
        AddGrad(pt.group, pt.off00 + pt.row + C, pt.w11 * gc);
        const uint cu = PlaneU(c), cv = PlaneV(c);
        const float wu = taps[cu].w, wv = taps[cv].w;
        const float du = gc * ((1.0 - wv) * (v[c][1] - v[c][0]) + wv * (v[c][3] - v[c][2]));
        dp[cu] += du * taps[cu].dpx;
        if (cv != 3u) {  // time is not a parameter
          const float dv = gc * ((1.0 - wu) * (v[c][2] - v[c][0]) + wu * (v[c][3] - v[c][1]));
          dp[cv] += dv * taps[cv].dpx;
        }
      }
    }
  }
  red[0][tid] = dp[0];
  red[1][tid] = dp[1];
  red[2][tid] = dp[2];
  memoryBarrierShared();
  barrier();
  for (uint h = LANES / 2u; h > 0u; h >>= 1u) {
    if (lane < h) {
      red[0][tid] += red[0][tid + h];
      red[1][tid] += red[1][tid + h];
      red[2][tid] += red[2][tid + h];
    }
    memoryBarrierShared();
    barrier();
  }
  if (lane == 0u && g < pc.rows) {
    d_means[g * 3u] = red[0][tid] * pc.ax;
    d_means[g * 3u + 1u] = red[1][tid] * pc.ay;
    d_means[g * 3u + 2u] = red[2][tid] * pc.az;
  }
}
