// Stage e: for each visible Gaussian in depth order (rank j), one instance per tile of its rect,
// row-major, at the offsets of the touched-tiles scan. Packed mode (tile and rank bits fit 32):
// key = tile << rank_bits | j, no value. Else key = tile, value = j. Writes past the instance
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
  uint rank_bits;  // 0: pair mode
} pc;

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  const uvec2 r = rects[sorted_ids[j]];
  const uint x0 = r.x & 0xffffu, y0 = r.x >> 16u, x1 = r.y & 0xffffu, y1 = r.y >> 16u;
  const uint begin = offsets[j];
  const uint end = min(begin + (x1 - x0) * (y1 - y0), pc.capacity);
  // One flat loop (not rows x columns): lanes with rects of different widths stay converged.
  uint tile = y0 * pc.tiles_x + x0;
  uint tx = x0;
  for (uint k = begin; k < end; ++k) {
    if (pc.rank_bits != 0u) {
      inst_keys[k] = (tile << pc.rank_bits) | j;
    } else {
      inst_keys[k] = tile;
      inst_vals[k] = j;
    }
    ++tx;
    const bool wrap = tx == x1;
    tile = wrap ? tile + 1u + pc.tiles_x - (x1 - x0) : tile + 1u;
    tx = wrap ? x0 : tx;
  }
}
