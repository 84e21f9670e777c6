// Shared layout of the vulkan backend's kernels. render/vulkan/stages.h mirrors the COUNT_* and
// ARGS_* indices and the block sizes on the host; change both together.
#ifndef STREETSIM_COMMON_GLSL_
#define STREETSIM_COMMON_GLSL_

// --- Work decomposition -------------------------------------------------------------------------
#define WG_SIZE 256              // threads per workgroup of the 1D kernels
#define SCAN_ITEMS 4             // items per thread in the block scan
#define SCAN_BLOCK 1024          // WG_SIZE * SCAN_ITEMS
#define SORT_ITEMS 32            // keys per thread in the radix passes
#define SORT_BLOCK 8192          // WG_SIZE * SORT_ITEMS
#define RANGE_ITEMS 4            // instances per thread in tile_ranges
#define RADIX_BITS 4
#define RADIX 16
#define TILE_SIZE 16
#define MAX_GRID_X 16384         // grids wider than this go 2D (pipeline.h: GridFor)

// --- The counts buffer (uint[]): element counts produced and consumed on the device -------------
#define COUNT_N 0           // Gaussians (host-written at frame start)
#define COUNT_V 1           // visible Gaussians (total of the visibility scan)
#define COUNT_I 2           // tile instances (total of the touched-tiles scan, saturating)
#define COUNT_IC 3          // min(I, instance capacity): what the tile sort and ranges process
#define COUNT_DEPTH_HIST 4  // 16 * depth-sort blocks (length of its histogram scan)
#define COUNT_TILE_HIST 5   // 16 * tile-sort blocks
#define COUNT_SINK 6        // scan totals nobody needs land here
#define NUM_COUNTS 16

// --- The args buffer (uvec4[]): VkDispatchIndirectCommand in .xyz of each slot -------------------
#define ARGS_V_SCAN 0            // 4 levels of the scan over V
#define ARGS_DEPTH_SORT 4        // depth radix blocks
#define ARGS_DEPTH_HIST_SCAN 5   // 4 levels
#define ARGS_V_THREADS 9         // one thread per visible Gaussian
#define ARGS_TILE_SORT 10        // tile radix blocks
#define ARGS_TILE_HIST_SCAN 11   // 4 levels
#define ARGS_IC_THREADS 15       // tile_ranges: RANGE_ITEMS tile instances per thread
#define NUM_ARGS 16
#define MAX_SCAN_LEVELS 4

// --- Per-Gaussian records ------------------------------------------------------------------------
// Gaussian parameters (uploaded once), 3 vec4 per Gaussian:
//   [0] = (mean xyz, opacity logit), [1] = (log-scale xyz, 0), [2] = quaternion (w, x, y, z).
// SH coefficients (K = (degree + 1)^2 per colour) in up to 4 groups of SH_GROUP coefficients,
// one buffer each, [i][k % SH_GROUP][rgb] within group k / SH_GROUP: no per-Gaussian record is
// larger than 48 bytes, so scenes of maxStorageBufferRange / 48 Gaussians fit (lavapipe: 128 MiB,
// 2.8M Gaussians) whatever the SH degree.
#define SH_GROUP 4u
uint ShGroupFloats(uint K, uint g) {
  return 3u * min(SH_GROUP, K > g * SH_GROUP ? K - g * SH_GROUP : 0u);
}
// Projected splat, 3 vec4 per Gaussian (written by project.comp for visible Gaussians only, by
// Gaussian id; gather_sorted.comp copies them into depth order for the blender):
//   [0] = (x, y, conic a, conic b), [1] = (conic c, opacity, r, g),
//   [2] = (b, depth, band half height, 0): the blender loads the first 10 words.
// dL/d(splat) of the backward, SPLAT_GRAD_STRIDE floats per visible Gaussian by depth rank, in
// the order of render/cpu/project_backward.h's SplatGradIndex:
#define SPLAT_GRAD_STRIDE 12u
#define SG_X 0u
#define SG_Y 1u
#define SG_A 2u
#define SG_B 3u
#define SG_C 4u
#define SG_O 5u
#define SG_R 6u
#define SG_G 7u
#define SG_BL 8u
#define SG_DEPTH 9u
// The deterministic backward's per-tile-instance partial sums (blend_backward.glsl): SG_X..SG_DEPTH.
#define DET_SLOT_FLOATS 10u
// Parameter gradients of the backward, 4 vec4 per Gaussian (zero where not visible):
//   [0] = (d mean xyz, d opacity logit), [1] = (d log-scale xyz, screen radius),
//   [2] = d quaternion (w, x, y, z), [3] = (d u, d v of the 2D mean, 0, 0);
// SH gradients in the scene's SH group layout.
// Tile rect, uvec2 per Gaussian: (x0 | y0 << 16, x1 | y1 << 16), half-open, in tiles.

uint linear_group_id() { return gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x; }
uint linear_thread_id() { return linear_group_id() * WG_SIZE + gl_LocalInvocationID.x; }

uint div_up(uint a, uint b) { return a / b + ((a % b) != 0u ? 1u : 0u); }

#endif  // STREETSIM_COMMON_GLSL_
