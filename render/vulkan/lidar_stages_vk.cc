// The vulkan LiDAR sweep's stages (lidar_stages_vk.h). The sequence is the camera frame's
// (project.cc, binning.cc, blend.cc) with the LiDAR's projection, compaction, gather and blend:
// range order within a tile, ties by entry index (Gaussian, then its seam copy), falls out of the
// compaction in entry order, the stable range sort and the stable tile sort, as for the camera.
#include "render/vulkan/lidar_stages_vk.h"

#include <algorithm>
#include <bit>

#include "render/vulkan/lidar_backward_vk.h"
#include "streetsim_spirv.h"

namespace streetsim::vulkan {

absl::StatusOr<std::unique_ptr<LidarKernels>> LidarKernels::Create(const Context& ctx) {
  auto k = std::make_unique<LidarKernels>();
  auto shared = Kernels::Create(ctx);
  if (!shared.ok()) return shared.status();
  k->shared = *std::move(shared);
  const SpecConstant rolling[] = {{0, 1}};
  const PipelineSpec specs[] = {
      {&k->project, "lidar_project", spirv::lidar_project, 7, sizeof(LidarProjectPush), {}},
      {&k->project_rolling, "lidar_project_rolling", spirv::lidar_project, 7, sizeof(LidarProjectPush),
       rolling},
      {&k->compact, "lidar_compact", spirv::lidar_compact, 6, 4, {}},
      {&k->gather, "lidar_gather", spirv::lidar_gather, 6, 4, {}},
      {&k->blend, "lidar_blend", spirv::lidar_blend, 5, sizeof(LidarBlendPush), {}},
      {&k->project_backward, "lidar_project_backward", spirv::lidar_project_backward, 6,
       sizeof(LidarProjectPush), {}},
  };
  if (absl::Status s = CreatePipelines(ctx, specs); !s.ok()) return s;
  if (ctx.has_subgroup_arithmetic()) {
    const bool native = ctx.has_float_atomic_add();
    auto p = ComputePipeline::Create(ctx, native ? "lidar_blend_backward" : "lidar_blend_backward_cas",
                                     native ? spirv::lidar_blend_backward : spirv::lidar_blend_backward_cas,
                                     7, sizeof(LidarBackwardPush));
    if (!p.ok()) return p.status();
    k->blend_backward = *std::move(p);
  }
  return k;
}

int LidarRangeKeyBits(float near_m, float far_m) {
  const uint32_t span = std::bit_cast<uint32_t>(far_m) - std::bit_cast<uint32_t>(near_m);
  return std::max(1, static_cast<int>(std::bit_width(span)));
}

namespace {

struct SetupPush {  // shaders/setup_args.comp
  uint32_t mode;
  uint32_t instance_capacity;
};

}  // namespace

void RecordLidarProject(Recorder& rec, const LidarKernels& k, const ScanScratch& scratch,
                        const LidarFrameBuffers& f, const Buffer& counts, const Buffer& args,
                        const LidarProjectPush& push) {
  const uint64_t entries = uint64_t{push.n} * 2;
  rec.Dispatch(push.rolling != 0 ? *k.project_rolling : *k.project,
               {f.gauss, f.table, f.reflectance, f.splats, f.rects, f.flags, f.touched}, push,
               GridFor(DivUp(push.n, kWorkgroupSize)));
  rec.Barrier();
  RecordScan(rec, *k.shared, scratch, *f.flags, counts, kCountN, entries, kCountV,
             /*saturate=*/false, Launch{nullptr, 0, entries});
  rec.Dispatch(*k.compact, {f.flags, f.touched, f.splats, f.keys[0], f.ids[0], &counts},
               std::bit_cast<uint32_t>(push.near_m), GridFor(DivUp(entries, kWorkgroupSize)));
  rec.Barrier();
  rec.Dispatch(*k.shared->setup_args, {&counts, &args}, SetupPush{0, 0}, Grid{1, 1});
  rec.Barrier();
}

BinningResult RecordLidarSortAndBin(Recorder& rec, const LidarKernels& k, const ScanScratch& scratch,
                                    const LidarFrameBuffers& f, const Buffer& counts,
                                    const Buffer& args, uint32_t num_entries,
                                    uint64_t instance_capacity, uint32_t splat_capacity,
                                    int range_key_bits, uint32_t tiles_x, uint32_t tiles_y,
                                    uint32_t rank_bits) {
  const Kernels& ks = *k.shared;
  // c. Range sort over the key bits that vary (LidarRangeKeyBits).
  const SortBuffers range_bufs{{f.keys[0], f.keys[1]}, {f.ids[0], f.ids[1]}, f.hist};
  const int d = RecordRadixSort(rec, ks, scratch, range_bufs, counts, kCountV, kCountDepthHist,
                                num_entries, 0, range_key_bits, Launch{&args, kArgsDepthSort},
                                Launch{&args, kArgsDepthHistScan});

  // d. Gather in range order, tiles touched -> instance offsets (I -> counts[kCountI], saturating).
  rec.DispatchIndirect(*k.gather,
                       {f.ids[d], f.touched, f.touched_sorted, &counts, f.splats, f.sorted_splats},
                       splat_capacity, args, kArgsVThreads * kArgsSlotBytes);
  rec.Barrier();
  // e..g as for the camera (instances name the entry's range rank j; tile ranges cleared at the
  // start of the sweep).
  const BinningBuffers bins{{f.inst_keys[0], f.inst_keys[1]}, {f.inst_vals[0], f.inst_vals[1]}, f.hist, f.ranges};
  return RecordEmitAndBin(rec, ks, scratch, {f.ids[d], f.touched_sorted, f.rects}, bins, counts, args,
                          num_entries, instance_capacity, tiles_x, tiles_y, rank_bits);
}

void RecordLidarBlend(Recorder& rec, const LidarKernels& k, const LidarFrameBuffers& f,
                      const BinningResult& bins, LidarBlendPush push, uint32_t tiles_y) {
  push.rank_mask = bins.rank_mask;
  rec.Dispatch(*k.blend, {f.ranges, bins.list, f.sorted_splats, f.planes, f.ray_state}, push,
               Grid{push.tiles_x, tiles_y});
  rec.Barrier();
}

}  // namespace streetsim::vulkan
