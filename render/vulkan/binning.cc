// Stages c..g: depth sort of the visible Gaussians, their tiles-touched offsets, emission of
// (tile, Gaussian) instances in depth order, the stable tile sort (only the bits a tile id needs)
// and the per-tile ranges. Depth order within a tile, ties broken by Gaussian index, falls out of
// sorting stably twice: the compacted list is in index order, the depth sort is stable over it,
// and the tile sort is stable over the depth-ordered instances.
#include <algorithm>
#include <bit>

#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

int TileBits(uint32_t num_tiles) {
  return num_tiles <= 1 ? 0 : static_cast<int>(std::bit_width(num_tiles - 1));
}

uint32_t RankBits(uint32_t num_gaussians, uint32_t num_tiles) {
  const uint32_t rank_bits =
      std::max<uint32_t>(1, num_gaussians <= 1 ? 1 : std::bit_width(num_gaussians - 1));
  return rank_bits + TileBits(num_tiles) <= 32 ? rank_bits : 0;
}

BinningResult RecordEmitAndBin(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                               const EmitSources& src, const BinningBuffers& bins, const Buffer& counts,
                               const Buffer& args, uint32_t num_entries, uint64_t instance_capacity,
                               uint32_t tiles_x, uint32_t tiles_y, uint32_t rank_bits) {
  RecordScan(rec, k, scratch, *src.touched_sorted, counts, kCountV, num_entries, kCountI,
             /*saturate=*/true, Launch{&args, kArgsVScan});
  struct SetupPush {
    uint32_t mode;
    uint32_t instance_capacity;
  };
  rec.Dispatch(*k.setup_args, {&counts, &args},
               SetupPush{1, static_cast<uint32_t>(instance_capacity)}, Grid{1, 1});
  rec.Barrier();

  // e. Emit.
  const bool packed = rank_bits != 0;
  struct EmitPush {
    uint32_t tiles_x;
    uint32_t capacity;
    uint32_t rank_bits;
  };
  rec.DispatchIndirect(*k.emit,
                       {src.sorted_ids, src.touched_sorted, src.rects, bins.inst_keys[0],
                        packed ? bins.inst_keys[0] : bins.inst_vals[0], &counts},
                       EmitPush{tiles_x, static_cast<uint32_t>(instance_capacity), rank_bits}, args,
                       kArgsVThreads * kArgsSlotBytes);
  rec.Barrier();

  // f. Stable tile sort over min(I, capacity) instances, by the tile bits only.
  const SortBuffers inst_bufs{
      {bins.inst_keys[0], bins.inst_keys[1]},
      {packed ? nullptr : bins.inst_vals[0], packed ? nullptr : bins.inst_vals[1]},
      bins.hist};
  const int t =
      RecordRadixSort(rec, k, scratch, inst_bufs, counts, kCountIc, kCountTileHist,
                      instance_capacity, static_cast<int>(rank_bits), TileBits(tiles_x * tiles_y),
                      Launch{&args, kArgsTileSort}, Launch{&args, kArgsTileHistScan});

  // g. Tile ranges (the caller cleared them: at the start of the frame / sweep).
  rec.DispatchIndirect(*k.tile_ranges, {bins.inst_keys[t], bins.ranges, &counts}, rank_bits, args,
                       kArgsIcThreads * kArgsSlotBytes);
  rec.Barrier();
  return BinningResult{packed ? bins.inst_keys[t] : bins.inst_vals[t],
                       packed ? (1u << rank_bits) - 1 : ~0u, src.sorted_ids};
}

BinningResult RecordSortAndBin(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                               const SceneBuffers& scene, const BinningBuffers& bins,
                               const Buffer& counts, const Buffer& args, uint32_t num_gaussians,
                               uint64_t instance_capacity, uint32_t tiles_x, uint32_t tiles_y,
                               uint32_t rank_bits) {
  // c. Depth sort; keys are float bits of depths > 0, so all 32 bits take part.
  const SortBuffers depth_bufs{
      {scene.depth_keys[0], scene.depth_keys[1]}, {scene.ids[0], scene.ids[1]}, bins.hist};
  const int d =
      RecordRadixSort(rec, k, scratch, depth_bufs, counts, kCountV, kCountDepthHist, num_gaussians,
                      0, 32, Launch{&args, kArgsDepthSort}, Launch{&args, kArgsDepthHistScan});

  // d. Tiles touched in depth order -> instance offsets; I -> counts[kCountI]. Saturating, so a
  // pathological total reads as 0xffffffff (> any capacity) instead of wrapping.
  rec.DispatchIndirect(*k.gather_sorted,
                       {scene.ids[d], scene.touched, scene.touched_sorted, &counts, scene.splats,
                        scene.sorted_splats},
                       args, kArgsVThreads * kArgsSlotBytes);
  rec.Barrier();
  return RecordEmitAndBin(rec, k, scratch, {scene.ids[d], scene.touched_sorted, scene.rects}, bins, counts,
                          args, num_gaussians, instance_capacity, tiles_x, tiles_y, rank_bits);
}

}  // namespace streetsim::vulkan
