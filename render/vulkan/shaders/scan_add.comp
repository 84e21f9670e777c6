// Exclusive prefix sum, add-back: adds the scanned total of each earlier block (level k+1) to the
// elements of level k.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_control_flow_attributes : require
#include "common.glsl"

layout(constant_id = 0) const uint kSaturate = 0u;

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) buffer Data { uint data[]; };
layout(std430, binding = 1) readonly buffer Sums { uint sums[]; };
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint n_index;
  uint level;
  uint data_offset;
  uint sums_offset;
} pc;

void main() {
  uint n = counts[pc.n_index];
  for (uint l = 0u; l < pc.level; ++l) n = div_up(n, SCAN_BLOCK);
  const uint block = linear_group_id();
  if (block == 0u || block >= div_up(n, SCAN_BLOCK)) return;  // block 0 adds 0
  const uint add = sums[pc.sums_offset + block];
  const uint first = block * SCAN_BLOCK + gl_LocalInvocationID.x * SCAN_ITEMS;
  [[unroll]] for (uint k = 0u; k < SCAN_ITEMS; ++k) {
    const uint idx = first + k;
    if (idx < n) {
      const uint s = data[pc.data_offset + idx] + add;
      data[pc.data_offset + idx] = (kSaturate != 0u && s < add) ? 0xffffffffu : s;
    }
  }
}
