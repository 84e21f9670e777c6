// LSD radix sort, pass part 1: 16-bin histogram of one 4-bit digit per block of SORT_BLOCK keys,
// written digit-major (hist[digit * num_blocks + block]) so that one exclusive scan of hist gives
// every (digit, block) its output offset. Subgroup-free: correct for any subgroup size.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_control_flow_attributes : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer Keys { uint keys[]; };
layout(std430, binding = 1) writeonly buffer Hist { uint hist[]; };
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint n_index;
  uint shift;
} pc;

// Per-thread digit counts packed two per uint (16 bits each; a block has at most 8192 keys).
shared uint s_cnt[8 * WG_SIZE];
shared uint s_part[8 * (WG_SIZE / 8)];

void main() {
  const uint n = counts[pc.n_index];
  const uint num_blocks = div_up(n, SORT_BLOCK);
  const uint block = linear_group_id();
  if (block >= num_blocks) return;
  const uint tid = gl_LocalInvocationID.x;
  const uint first = block * SORT_BLOCK + tid * SORT_ITEMS;

  uvec4 lo = uvec4(0u), hi = uvec4(0u);  // words 0..3 (digits 0..7), 4..7 (digits 8..15)
  [[unroll]] for (uint k = 0u; k < SORT_ITEMS; ++k) {
    const uint idx = first + k;
    if (idx < n) {
      const uint d = (keys[idx] >> pc.shift) & (RADIX - 1u);
      const uint w = d >> 1u;
      const uint inc = 1u << ((d & 1u) * 16u);
      lo += uvec4(equal(uvec4(0u, 1u, 2u, 3u), uvec4(w))) * inc;
      hi += uvec4(equal(uvec4(4u, 5u, 6u, 7u), uvec4(w))) * inc;
    }
  }
  [[unroll]] for (uint w = 0u; w < 4u; ++w) {
    s_cnt[w * WG_SIZE + tid] = lo[w];
    s_cnt[(w + 4u) * WG_SIZE + tid] = hi[w];
  }
  barrier();
  {
    // 256 threads = 8 words x 32 segments of 8 threads.
    const uint w = tid & 7u, seg = tid >> 3u;
    uint acc = 0u;
    for (uint k = 0u; k < 8u; ++k) acc += s_cnt[w * WG_SIZE + seg * 8u + k];
    s_part[w * (WG_SIZE / 8u) + seg] = acc;
  }
  barrier();
  if (tid < 8u) {
    uint acc = 0u;
    for (uint k = 0u; k < WG_SIZE / 8u; ++k) acc += s_part[tid * (WG_SIZE / 8u) + k];
    hist[(2u * tid) * num_blocks + block] = acc & 0xffffu;
    hist[(2u * tid + 1u) * num_blocks + block] = acc >> 16u;
  }
}
