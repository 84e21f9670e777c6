// Stage b (after the scan of the visibility flags): visible Gaussian ids in index order, with
// their depth keys. Deterministic: positions come from the scan, not from atomics.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Offsets { uint offsets[]; };
layout(std430, binding = 1) readonly buffer Touched { uint touched[]; };
layout(std430, binding = 2) readonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 3) writeonly buffer Keys { uint keys[]; };
layout(std430, binding = 4) writeonly buffer Ids { uint ids[]; };
layout(std430, binding = 5) readonly buffer Counts { uint counts[]; };

void main() {
  const uint i = linear_thread_id();
  if (i >= counts[COUNT_N] || touched[i] == 0u) return;
  const uint pos = offsets[i];
  // Depth > near plane (0.2) > 0, so the float bits order like the floats.
  keys[pos] = floatBitsToUint(splats[3u * i + 2u].y);
  ids[pos] = i;
}
