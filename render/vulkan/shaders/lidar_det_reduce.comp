// Deterministic LiDAR backward, step 3: one thread per Gaussian i sums the slots of entry 2i, then
// those of its seam copy 2i + 1, each in emit order (a rank's instances are contiguous:
// offsets[j] .. offsets[j + 1]), into dL/d(splat terms) for lidar_project_backward.comp.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

#define GRAD_STRIDE 8u  // lidar_blend_backward.glsl

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer RankOf { uint rank_of[]; };
layout(std430, binding = 1) readonly buffer Offsets { uint offsets[]; };  // exclusive scan by rank
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 3) readonly buffer Slots { float slots[]; };
layout(std430, binding = 4) writeonly buffer SplatGrads { float splat_grads[]; };
layout(push_constant, std430) uniform Params {
  uint n;              // Gaussians
  uint slot_capacity;  // slots in the buffer
  uint splat_capacity; // ranks the tile lists can name (lidar_blend_backward.glsl clamps to it)
} pc;

void main() {
  const uint i = linear_thread_id();
  if (i >= pc.n) return;
  const uint V = counts[COUNT_V];
  vec4 s0 = vec4(0.0), s1 = vec4(0.0);
  for (uint copy = 0u; copy < 2u; ++copy) {
    const uint j = rank_of[2u * i + copy];
    if (j >= V || j >= pc.splat_capacity) continue;
    const uint begin = offsets[j];
    const uint end = min(j + 1u < V ? offsets[j + 1u] : counts[COUNT_I], pc.slot_capacity);
    for (uint e = begin; e < end; ++e) {
      const uint o = e * GRAD_STRIDE;
      s0 += vec4(slots[o], slots[o + 1u], slots[o + 2u], slots[o + 3u]);
      s1 += vec4(slots[o + 4u], slots[o + 5u], slots[o + 6u], slots[o + 7u]);
    }
  }
  const uint o = i * GRAD_STRIDE;
  splat_grads[o] = s0.x;
  splat_grads[o + 1u] = s0.y;
  splat_grads[o + 2u] = s0.z;
  splat_grads[o + 3u] = s0.w;
  splat_grads[o + 4u] = s1.x;
  splat_grads[o + 5u] = s1.y;
  splat_grads[o + 6u] = s1.z;
  splat_grads[o + 7u] = s1.w;
}
