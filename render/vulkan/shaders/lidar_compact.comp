// LiDAR stage b (after the scan of the entries' drawn flags): drawn entries in entry order (a
// Gaussian's splat before its seam copy) with their range keys, so that the stable range sort
// breaks ties by Gaussian index as the cpu renderer does. Deterministic: positions come from the
// scan, not from atomics. The key is the range's float bits minus those of the near cull: the same
// order (ranges are in (near, far)), in fewer bits, so the radix sort can skip a pass.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Offsets { uint offsets[]; };
layout(std430, binding = 1) readonly buffer Touched { uint touched[]; };
layout(std430, binding = 2) readonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 3) writeonly buffer Keys { uint keys[]; };
layout(std430, binding = 4) writeonly buffer Ids { uint ids[]; };
layout(std430, binding = 5) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint key_base;  // float bits of the near cull distance
} pc;

void main() {
  const uint e = linear_thread_id();
  if (e >= counts[COUNT_N] || touched[e] == 0u) return;
  const uint pos = offsets[e];
  // near < range < far, all > 0: the float bits order like the floats.
  keys[pos] = floatBitsToUint(splats[3u * (e >> 1u) + 2u].y) - pc.key_base;
  ids[pos] = e;
}
