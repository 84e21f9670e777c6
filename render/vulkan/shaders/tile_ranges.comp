// Stage g: [start, end) of each tile's run in the tile-sorted instance list. The ranges buffer is
// cleared first, so tiles without instances stay empty (0, 0).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Keys { uint inst_keys[]; };
layout(std430, binding = 1) writeonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };

void main() {
  const uint i = linear_thread_id();
  const uint n = counts[COUNT_IC];
  if (i >= n) return;
  const uint t = inst_keys[i];
  if (i == 0u || inst_keys[i - 1u] != t) ranges[t].x = i;
  if (i + 1u == n || inst_keys[i + 1u] != t) ranges[t].y = i + 1u;
}
