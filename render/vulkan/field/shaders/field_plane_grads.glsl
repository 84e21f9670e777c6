// Plane-gradient buffers (bindings 8..11, grouped as the planes) and the bilinear splat of one
// plane sample's dL/d(sample), shared by the base field's feature backward
// (field_sample_backward.glsl) and the extended field's token backward
// (render/vulkan/field/ext/shaders/ext_sample_backward.glsl). Float atomicAdd
// (VK_EXT_shader_atomic_float) unless CAS_ATOMICS is defined, then a compare-and-swap loop.
// Include after field_sample_backward_head.glsl (atomics, `means`, `d_means`, LANES) and the push
// constants `pc` (ax, ay, az, bx, by, bz, rows).
#ifndef STREETSIM_FIELD_PLANE_GRADS_GLSL_
#define STREETSIM_FIELD_PLANE_GRADS_GLSL_

#ifdef CAS_ATOMICS
#define GRAD_T uint
#else
#define GRAD_T float
#endif
layout(std430, binding = 8) buffer Grads0 { GRAD_T grads0[]; };
layout(std430, binding = 9) buffer Grads1 { GRAD_T grads1[]; };
layout(std430, binding = 10) buffer Grads2 { GRAD_T grads2[]; };
layout(std430, binding = 11) buffer Grads3 { GRAD_T grads3[]; };

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

// Gaussian g's sampling coordinates p = a * mean + b.
float[3] SampleCoords(uint g) {
  return float[3](pc.ax * means[g * 3u] + pc.bx, pc.ay * means[g * 3u + 1u] + pc.by,
                  pc.az * means[g * 3u + 2u] + pc.bz);
}

// The 4 texel values of one sample (v00, v01, v10, v11) and the sample itself.
float LoadSample(PlaneTaps pt, out float v[4]) {
  v[0] = LoadPlane(pt.group, pt.off00);
  v[1] = LoadPlane(pt.group, pt.off00 + CHANNELS);
  v[2] = LoadPlane(pt.group, pt.off00 + pt.row);
  v[3] = LoadPlane(pt.group, pt.off00 + pt.row + CHANNELS);
  return pt.w00 * v[0] + pt.w01 * v[1] + pt.w10 * v[2] + pt.w11 * v[3];
}

// Splats gc = dL/d(sample) onto the sample's 4 texels; returns dL/d(u, v) of its continuous texel
// coordinates (wu, wv: the upper texels' weights), as internal::SampleCoordGrad.
vec2 SplatSample(PlaneTaps pt, float v[4], float wu, float wv, float gc) {
  AddGrad(pt.group, pt.off00, pt.w00 * gc);
  AddGrad(pt.group, pt.off00 + CHANNELS, pt.w01 * gc);
  AddGrad(pt.group, pt.off00 + pt.row, pt.w10 * gc);
  AddGrad(pt.group, pt.off00 + pt.row + CHANNELS, pt.w11 * gc);
  return vec2(gc * ((1.0 - wv) * (v[1] - v[0]) + wv * (v[3] - v[2])),
              gc * ((1.0 - wu) * (v[2] - v[0]) + wu * (v[3] - v[1])));
}

// Sums the LANES invocations' shares dp of one Gaussian's dL/d(texel coordinate) per axis in
// shared memory (fixed order: deterministic) and writes dL/d(mean) = sum * d(p)/d(mean). Every
// invocation of the workgroup must call it (barriers).
shared float lane_red[3][256];
void WriteMeanGrads(uint tid, uint lane, uint g, float dp[3]) {
  lane_red[0][tid] = dp[0];
  lane_red[1][tid] = dp[1];
  lane_red[2][tid] = dp[2];
  memoryBarrierShared();
  barrier();
  for (uint h = LANES / 2u; h > 0u; h >>= 1u) {
    if (lane < h) {
      lane_red[0][tid] += lane_red[0][tid + h];
      lane_red[1][tid] += lane_red[1][tid + h];
      lane_red[2][tid] += lane_red[2][tid + h];
    }
    memoryBarrierShared();
    barrier();
  }
  if (lane == 0u && g < pc.rows) {
    d_means[g * 3u] = lane_red[0][tid] * pc.ax;
    d_means[g * 3u + 1u] = lane_red[1][tid] * pc.ay;
    d_means[g * 3u + 2u] = lane_red[2][tid] * pc.az;
  }
}

#endif  // STREETSIM_FIELD_PLANE_GRADS_GLSL_
