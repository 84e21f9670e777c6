// The vulkan LiDAR sweep's stages as recording functions over a Recorder (internal to
// lidar_renderer_vk.cc). The LiDAR's own kernels are the projection, the compaction of drawn
// entries, the range-order gather and the blend (shaders/lidar_*.comp); the scans, radix sorts,
// setup_args, emit and tile_ranges are the camera frame's kernels (stages.h) run over "entries":
// entry 2i is Gaussian i's splat, entry 2i + 1 its copy one turn away when it crosses the seam.
#pragma once

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

struct LidarKernels {
  std::unique_ptr<Kernels> shared;  // the camera frame's kernels
  // project_rolling: the projection with one pose per column (specialization constant).
  std::unique_ptr<ComputePipeline> project, project_rolling, compact, gather, blend;
  // Backward (lidar_backward_vk.h). blend_backward is null on devices without subgroup arithmetic
  // (VulkanLidarRenderer::Backward is then FailedPrecondition); it uses float atomic adds where the
  // device has them, a compare-and-swap loop otherwise.
  std::unique_ptr<ComputePipeline> blend_backward, project_backward;
  // Deterministic mode (lidar_backward_vk.h): per-tile-instance slots, the range order's inverse
  // and the per-Gaussian fixed-order sums; built on first use (EnsureLidarDeterministicKernels).
  std::unique_ptr<ComputePipeline> blend_backward_det, det_rank_of, det_reduce;
  static absl::StatusOr<std::unique_ptr<LidarKernels>> Create(const Context& ctx);
};

// Mirrors shaders/lidar_project.comp's push constants.
struct LidarProjectPush {
  uint32_t n;
  int32_t columns, beams, tiles_x, tiles_y;
  float near_m, far_m, cols_per_rad;
  uint32_t pose_offset;  // first float of the pose table in the sweep table
  uint32_t rolling;      // 0: one pose (the table's pose 0) for every column; picks the pipeline
  uint32_t has_refl;
};
static_assert(sizeof(LidarProjectPush) == 44);

// Mirrors shaders/lidar_blend.comp's push constants (rank_mask is filled from the binning).
struct LidarBlendPush {
  uint32_t columns, beams, tiles_x, rank_mask;
  float return_alpha_threshold;
  uint32_t sample_drop;
  uint32_t seed_lo, seed_hi;
  uint32_t splat_capacity;
};
static_assert(sizeof(LidarBlendPush) == 36);

struct LidarFrameBuffers {
  const Buffer* gauss;          // 3 vec4 per Gaussian (the camera scene's layout)
  const Buffer* table;          // the sweep table (lidar_common.glsl)
  const Buffer* reflectance;    // float per Gaussian (any buffer when has_refl == 0)
  const Buffer* splats;         // 3 vec4 per Gaussian
  const Buffer* sorted_splats;  // 3 vec4 per drawn entry, by range rank (splat_capacity of them)
  const Buffer* rects;          // uvec2 per entry
  const Buffer* flags;          // uint per entry: drawn, scanned in place to offsets
  const Buffer* touched;        // uint per entry
  const Buffer* touched_sorted;  // uint per entry, by range rank
  const Buffer* keys[2];        // uint per entry (range sort ping-pong)
  const Buffer* ids[2];
  const Buffer* inst_keys[2];   // tile instances (packed: tile << rank_bits | rank)
  const Buffer* inst_vals[2];   // pair mode only
  const Buffer* hist;
  const Buffer* ranges;         // uvec2 per tile
  const Buffer* planes;         // 5 float planes per ray (lidar_blend.comp)
  const Buffer* ray_state;      // 2 uint planes per ray: final T bits, last contributor
};

// Stages a, b: projection, the scan of the 2n entries' drawn flags (V -> counts[kCountV]), the
// compaction with range keys, setup_args mode 0.
void RecordLidarProject(Recorder& rec, const LidarKernels& k, const ScanScratch& scratch,
                        const LidarFrameBuffers& f, const Buffer& counts, const Buffer& args,
                        const LidarProjectPush& push);

// Key bits of the range sort: keys are float bits of the range minus those of near_m
// (lidar_compact.comp), below those of far_m - near_m (26 bits for 2.5 .. 120 m: 7 radix passes, not 8).
int LidarRangeKeyBits(float near_m, float far_m);

// Stages c..g: stable range sort, gather in range order (at most splat_capacity splat records),
// touched-tiles scan (I -> counts[kCountI]), emit, stable tile sort, tile ranges. rank_bits: as
// the camera's (stages.h: RankBits; 0 = pair mode). Returns the tile-sorted instance list.
BinningResult RecordLidarSortAndBin(Recorder& rec, const LidarKernels& k, const ScanScratch& scratch,
                                    const LidarFrameBuffers& f, const Buffer& counts,
                                    const Buffer& args, uint32_t num_entries,
                                    uint64_t instance_capacity, uint32_t splat_capacity,
                                    int range_key_bits, uint32_t tiles_x, uint32_t tiles_y,
                                    uint32_t rank_bits);

// Stage h: the blend and the outputs, one workgroup per tile.
void RecordLidarBlend(Recorder& rec, const LidarKernels& k, const LidarFrameBuffers& f,
                      const BinningResult& bins, LidarBlendPush push, uint32_t tiles_y);

}  // namespace streetsim::vulkan
