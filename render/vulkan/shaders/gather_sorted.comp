// Stage d: tiles touched by each visible Gaussian in depth order (the scan input for the instance
// offsets), and the splat records in depth order, so that the blender reads a tile's splats
// without an id indirection.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Ids { uint sorted_ids[]; };
layout(std430, binding = 1) readonly buffer Touched { uint touched[]; };
layout(std430, binding = 2) writeonly buffer Out { uint out_touched[]; };
layout(std430, binding = 3) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 4) readonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 5) writeonly buffer SortedSplats { vec4 sorted_splats[]; };

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  const uint gid = sorted_ids[j];
  out_touched[j] = touched[gid];
  sorted_splats[3u * j] = splats[3u * gid];
  sorted_splats[3u * j + 1u] = splats[3u * gid + 1u];
  sorted_splats[3u * j + 2u] = splats[3u * gid + 2u];
}
