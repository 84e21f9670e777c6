// Stage d: tiles touched by each visible Gaussian, in depth order (the scan input for offsets).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Ids { uint sorted_ids[]; };
layout(std430, binding = 1) readonly buffer Touched { uint touched[]; };
layout(std430, binding = 2) writeonly buffer Out { uint out_touched[]; };
layout(std430, binding = 3) readonly buffer Counts { uint counts[]; };

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  out_touched[j] = touched[sorted_ids[j]];
}
