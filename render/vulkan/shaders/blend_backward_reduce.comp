// Second pass of the deterministic blend backward: one thread per visible Gaussian (depth rank j)
// sums its tile instances' slots (blend_backward_det.comp) in emit order, i.e. its rect's tiles
// row-major, and writes dL/d(splat) for project_backward.comp. A rank's instances are contiguous
// (offsets[j] .. offsets[j + 1], the touched-tiles scan), so no search is needed.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Offsets { uint offsets[]; };  // exclusive scan by rank
layout(std430, binding = 1) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 2) readonly buffer Slots { float slots[]; };
layout(std430, binding = 3) writeonly buffer SplatGrads { float splat_grads[]; };
layout(push_constant, std430) uniform Params {
  uint slot_capacity;
} pc;

void main() {
  const uint j = linear_thread_id();
  const uint V = counts[COUNT_V];
  if (j >= V) return;
  const uint begin = offsets[j];
  const uint end = min(j + 1u < V ? offsets[j + 1u] : counts[COUNT_I], pc.slot_capacity);
  // Components by hand: one loop trip per instance (llvmpipe's loop limiter counts every trip).
  vec4 s0 = vec4(0.0), s1 = vec4(0.0);
  vec2 s2 = vec2(0.0);
  for (uint e = begin; e < end; ++e) {
    const uint o = e * DET_SLOT_FLOATS;
    s0 += vec4(slots[o], slots[o + 1u], slots[o + 2u], slots[o + 3u]);
    s1 += vec4(slots[o + 4u], slots[o + 5u], slots[o + 6u], slots[o + 7u]);
    s2 += vec2(slots[o + 8u], slots[o + 9u]);
  }
  const uint o = j * SPLAT_GRAD_STRIDE;
  splat_grads[o + SG_X] = s0.x;
  splat_grads[o + SG_Y] = s0.y;
  splat_grads[o + SG_A] = s0.z;
  splat_grads[o + SG_B] = s0.w;
  splat_grads[o + SG_C] = s1.x;
  splat_grads[o + SG_O] = s1.y;
  splat_grads[o + SG_R] = s1.z;
  splat_grads[o + SG_G] = s1.w;
  splat_grads[o + SG_BL] = s2.x;
  splat_grads[o + SG_DEPTH] = s2.y;
}
