// LiDAR stage d: for each drawn entry in range order (rank j), its tile count (the scan input for
// the instance offsets) and its splat record, the seam copy's column substituted, so that the
// blender reads a tile's splats without an id indirection. Records past the capacity of the sorted
// splat buffer are not written: the host sees V > capacity, grows it and renders again.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Ids { uint sorted_ids[]; };
layout(std430, binding = 1) readonly buffer Touched { uint touched[]; };
layout(std430, binding = 2) writeonly buffer Out { uint out_touched[]; };
layout(std430, binding = 3) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 4) readonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 5) writeonly buffer SortedSplats { vec4 sorted_splats[]; };
layout(push_constant, std430) uniform Params {
  uint capacity;  // splat records sorted_splats holds
} pc;

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  const uint e = sorted_ids[j];
  const uint i = e >> 1u;
  out_touched[j] = touched[e];
  if (j >= pc.capacity) return;
  vec4 s0 = splats[3u * i];
  const vec4 s2 = splats[3u * i + 2u];
  s0.x = (e & 1u) != 0u ? s2.z : s0.x;
  sorted_splats[3u * j] = s0;
  sorted_splats[3u * j + 1u] = splats[3u * i + 1u];
  sorted_splats[3u * j + 2u] = s2;
}
