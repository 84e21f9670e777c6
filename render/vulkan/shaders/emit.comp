// Stage e: for each visible Gaussian in depth order, one (tile id, Gaussian id) instance per tile
// of its rect, row-major, at the offsets of the touched-tiles scan. Writes past the instance
// capacity are dropped; the host sees I > capacity, grows the buffers and renders again.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Ids { uint sorted_ids[]; };
layout(std430, binding = 1) readonly buffer Offsets { uint offsets[]; };
layout(std430, binding = 2) readonly buffer Rects { uvec2 rects[]; };
layout(std430, binding = 3) writeonly buffer Keys { uint inst_keys[]; };
layout(std430, binding = 4) writeonly buffer Vals { uint inst_vals[]; };
layout(std430, binding = 5) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint tiles_x;
  uint capacity;
} pc;

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  const uint gid = sorted_ids[j];
  const uvec2 r = rects[gid];
  const uint x0 = r.x & 0xffffu, y0 = r.x >> 16u, x1 = r.y & 0xffffu, y1 = r.y >> 16u;
  uint k = offsets[j];
  for (uint ty = y0; ty < y1 && k < pc.capacity; ++ty) {
    for (uint tx = x0; tx < x1 && k < pc.capacity; ++tx) {
      inst_keys[k] = ty * pc.tiles_x + tx;
      inst_vals[k] = gid;
      ++k;
    }
  }
}
