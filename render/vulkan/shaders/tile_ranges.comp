// Stage g: [start, end) of each tile's run in the tile-sorted instance list. The ranges buffer is
// cleared first, so tiles without instances stay empty (0, 0). Each thread looks at the
// boundaries after RANGE_ITEMS consecutive instances.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Keys { uint inst_keys[]; };
layout(std430, binding = 1) writeonly buffer Ranges { uvec2 ranges[]; };
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint rank_bits;  // the tile id is key >> rank_bits
} pc;

void main() {
  const uint first = linear_thread_id() * RANGE_ITEMS;
  const uint n = counts[COUNT_IC];
  if (first >= n) return;
  uint t = inst_keys[first] >> pc.rank_bits;
  if (first == 0u) ranges[t].x = 0u;
  for (uint i = first; i < min(first + RANGE_ITEMS, n); ++i) {
    const uint next = i + 1u < n ? inst_keys[i + 1u] >> pc.rank_bits : 0xffffffffu;
    if (next != t) {
      ranges[t].y = i + 1u;
      if (i + 1u < n) ranges[next].x = i + 1u;
    }
    t = next;
  }
}
