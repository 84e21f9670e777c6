// LSD radix sort, pass part 2: stable scatter. Thread t owns SORT_ITEMS consecutive keys of its
// block, so the block order is (thread, item); a key's rank among same-digit keys of the block is
// (same-digit keys of earlier threads: a shared scan of packed per-thread counts) + (same-digit
// keys earlier in this thread). Subgroup-free: correct for any subgroup size.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_control_flow_attributes : require
#include "common.glsl"

// Keys-only sorts (packed tile instances) leave the value bindings untouched.
layout(constant_id = 0) const uint kKeysOnly = 0u;

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) readonly buffer KeysIn { uint keys_in[]; };
layout(std430, binding = 1) readonly buffer ValsIn { uint vals_in[]; };
layout(std430, binding = 2) writeonly buffer KeysOut { uint keys_out[]; };
layout(std430, binding = 3) writeonly buffer ValsOut { uint vals_out[]; };
layout(std430, binding = 4) readonly buffer Hist { uint hist[]; };  // scanned
layout(std430, binding = 5) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint n_index;
  uint shift;
} pc;

shared uint s_cnt[8 * WG_SIZE];
shared uint s_part[8 * (WG_SIZE / 8)];
shared uint s_offset[RADIX];

uint Extract(uvec4 lo, uvec4 hi, uint d) {
  const uint w = d >> 1u;
  const uvec4 mlo = uvec4(equal(uvec4(0u, 1u, 2u, 3u), uvec4(w)));
  const uvec4 mhi = uvec4(equal(uvec4(4u, 5u, 6u, 7u), uvec4(w)));
  const uvec4 m = mlo * lo + mhi * hi;
  const uint word = m.x + m.y + m.z + m.w;
  return (word >> ((d & 1u) * 16u)) & 0xffffu;
}

void main() {
  const uint n = counts[pc.n_index];
  const uint num_blocks = div_up(n, SORT_BLOCK);
  const uint block = linear_group_id();
  if (block >= num_blocks) return;
  const uint tid = gl_LocalInvocationID.x;
  const uint first = block * SORT_BLOCK + tid * SORT_ITEMS;
  if (tid < RADIX) s_offset[tid] = hist[tid * num_blocks + block];

  uint key[SORT_ITEMS];
  uint rank[SORT_ITEMS];  // digit in the low 4 bits, rank within this thread above
  uvec4 lo = uvec4(0u), hi = uvec4(0u);
  [[unroll]] for (uint k = 0u; k < SORT_ITEMS; ++k) {
    const uint idx = first + k;
    key[k] = idx < n ? keys_in[idx] : 0u;
    const uint d = (key[k] >> pc.shift) & (RADIX - 1u);
    rank[k] = d | (Extract(lo, hi, d) << 4u);
    const uint w = d >> 1u;
    const uint inc = idx < n ? 1u << ((d & 1u) * 16u) : 0u;
    lo += uvec4(equal(uvec4(0u, 1u, 2u, 3u), uvec4(w))) * inc;
    hi += uvec4(equal(uvec4(4u, 5u, 6u, 7u), uvec4(w))) * inc;
  }
  [[unroll]] for (uint w = 0u; w < 4u; ++w) {
    s_cnt[w * WG_SIZE + tid] = lo[w];
    s_cnt[(w + 4u) * WG_SIZE + tid] = hi[w];
  }
  barrier();
  {
    const uint w = tid & 7u, seg = tid >> 3u;
    uint acc = 0u;
    for (uint k = 0u; k < 8u; ++k) {
      const uint i = w * WG_SIZE + seg * 8u + k;
      const uint x = s_cnt[i];
      s_cnt[i] = acc;
      acc += x;
    }
    s_part[w * (WG_SIZE / 8u) + seg] = acc;
  }
  barrier();
  if (tid < 8u) {
    uint acc = 0u;
    for (uint k = 0u; k < WG_SIZE / 8u; ++k) {
      const uint i = tid * (WG_SIZE / 8u) + k;
      const uint x = s_part[i];
      s_part[i] = acc;
      acc += x;
    }
  }
  barrier();
  // This thread's exclusive prefix of the packed counts, one word per digit pair.
  uvec4 pre_lo, pre_hi;
  [[unroll]] for (uint w = 0u; w < 4u; ++w) {
    pre_lo[w] = s_cnt[w * WG_SIZE + tid] + s_part[w * (WG_SIZE / 8u) + (tid >> 3u)];
    pre_hi[w] = s_cnt[(w + 4u) * WG_SIZE + tid] + s_part[(w + 4u) * (WG_SIZE / 8u) + (tid >> 3u)];
  }
  [[unroll]] for (uint k = 0u; k < SORT_ITEMS; ++k) {
    const uint idx = first + k;
    if (idx >= n) continue;
    const uint d = rank[k] & (RADIX - 1u);
    const uint pos = s_offset[d] + Extract(pre_lo, pre_hi, d) + (rank[k] >> 4u);
    keys_out[pos] = key[k];
    if (kKeysOnly == 0u) vals_out[pos] = vals_in[idx];
  }
}
