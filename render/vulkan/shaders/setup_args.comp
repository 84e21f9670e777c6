// The 1-thread "setup args" kernel: turns counts produced on the device (V after the visibility
// scan, I after the instance scan) into VkDispatchIndirectCommand entries and derived counts, so
// the frame never waits on the host.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = 1) in;
layout(std430, binding = 0) buffer Counts { uint counts[]; };
layout(std430, binding = 1) writeonly buffer Args { uvec4 args[]; };
layout(push_constant, std430) uniform Params {
  uint mode;                // 0: after V is known, 1: after I is known
  uint instance_capacity;   // elements of the per-instance buffers
} pc;

void Write(uint slot, uint groups) {
  // Wide grids go 2D; kernels linearise and early-out past their count.
  if (groups <= MAX_GRID_X) {
    args[slot] = uvec4(groups, 1u, 1u, 0u);
  } else {
    args[slot] = uvec4(MAX_GRID_X, div_up(groups, MAX_GRID_X), 1u, 0u);
  }
}

void WriteScan(uint slot, uint n) {
  uint m = n;
  for (uint k = 0u; k < MAX_SCAN_LEVELS; ++k) {
    m = div_up(m, SCAN_BLOCK);
    Write(slot + k, m);
  }
}

void main() {
  if (pc.mode == 0u) {
    const uint v = counts[COUNT_V];
    const uint blocks = div_up(v, SORT_BLOCK);
    counts[COUNT_DEPTH_HIST] = blocks * RADIX;
    Write(ARGS_DEPTH_SORT, blocks);
    WriteScan(ARGS_DEPTH_HIST_SCAN, blocks * RADIX);
    Write(ARGS_V_THREADS, div_up(v, WG_SIZE));
    WriteScan(ARGS_V_SCAN, v);
  } else {
    const uint ic = min(counts[COUNT_I], pc.instance_capacity);
    counts[COUNT_IC] = ic;
    const uint blocks = div_up(ic, SORT_BLOCK);
    counts[COUNT_TILE_HIST] = blocks * RADIX;
    Write(ARGS_TILE_SORT, blocks);
    WriteScan(ARGS_TILE_HIST_SCAN, blocks * RADIX);
    Write(ARGS_IC_THREADS, div_up(ic, WG_SIZE * RANGE_ITEMS));
  }
}
