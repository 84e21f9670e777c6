// Exclusive prefix sum, one level: each workgroup scans SCAN_BLOCK consecutive uints in place and
// writes its block total to sums[]. Subgroup-free (shared memory + barriers only), so the result
// does not depend on the subgroup size. Level k scans ceil(n / SCAN_BLOCK^k) block totals of
// level k-1; the single block of the top level writes the grand total.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_control_flow_attributes : require
#include "common.glsl"

// Saturating adds (clamp at 0xffffffff) for scans whose total may exceed 32 bits: tile instances.
layout(constant_id = 0) const uint kSaturate = 0u;

layout(local_size_x = WG_SIZE) in;
layout(std430, binding = 0) buffer Data { uint data[]; };
layout(std430, binding = 1) buffer Sums { uint sums[]; };
layout(std430, binding = 2) readonly buffer Counts { uint counts[]; };
layout(push_constant, std430) uniform Params {
  uint n_index;      // counts[n_index] = level-0 element count
  uint level;
  uint data_offset;  // element offsets into data[] / sums[]
  uint sums_offset;
} pc;

uint add(uint a, uint b) {
  const uint s = a + b;
  return (kSaturate != 0u && s < a) ? 0xffffffffu : s;
}

shared uint s_part[WG_SIZE];
shared uint s_seg[WG_SIZE / 8];

void main() {
  uint n = counts[pc.n_index];
  for (uint l = 0u; l < pc.level; ++l) n = div_up(n, SCAN_BLOCK);
  const uint block = linear_group_id();
  if (block >= div_up(n, SCAN_BLOCK)) return;  // whole workgroup: barriers stay uniform
  const uint tid = gl_LocalInvocationID.x;
  const uint first = block * SCAN_BLOCK + tid * SCAN_ITEMS;

  uint v[SCAN_ITEMS];
  uint running = 0u;
  [[unroll]] for (uint k = 0u; k < SCAN_ITEMS; ++k) {
    const uint idx = first + k;
    const uint x = idx < n ? data[pc.data_offset + idx] : 0u;
    v[k] = running;
    running = add(running, x);
  }
  s_part[tid] = running;
  barrier();
  // Raking scan of the 256 thread totals: 32 segments of 8, then the 32 segment totals.
  if (tid < WG_SIZE / 8u) {
    uint acc = 0u;
    for (uint k = 0u; k < 8u; ++k) {
      const uint x = s_part[tid * 8u + k];
      s_part[tid * 8u + k] = acc;
      acc = add(acc, x);
    }
    s_seg[tid] = acc;
  }
  barrier();
  if (tid == 0u) {
    uint acc = 0u;
    for (uint k = 0u; k < WG_SIZE / 8u; ++k) {
      const uint x = s_seg[k];
      s_seg[k] = acc;
      acc = add(acc, x);
    }
    sums[pc.sums_offset + block] = acc;
  }
  barrier();
  const uint prefix = add(s_seg[tid / 8u], s_part[tid]);
  [[unroll]] for (uint k = 0u; k < SCAN_ITEMS; ++k) {
    const uint idx = first + k;
    if (idx < n) data[pc.data_offset + idx] = add(prefix, v[k]);
  }
}
