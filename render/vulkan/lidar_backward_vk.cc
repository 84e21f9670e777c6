// The vulkan LiDAR backward pass's stages (lidar_backward_vk.h).
#include "render/vulkan/lidar_backward_vk.h"

#include <algorithm>
#include <cstring>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "streetsim_spirv.h"

namespace streetsim::vulkan {

absl::Status EnsureLidarDeterministicKernels(const Context& ctx, LidarKernels* k) {
  if (k->blend_backward_det != nullptr) return absl::OkStatus();
  const uint32_t subgroup = ctx.subgroup().size;
  if (!ctx.has_subgroup_arithmetic()) {
    return absl::FailedPreconditionError(absl::StrCat(
        ctx.description(), ": the LiDAR backward pass needs subgroup arithmetic operations"));
  }
  // lidar_blend_backward.glsl sums at most 16 subgroups (unrolled), of at most 64 lanes.
  if (subgroup < 4 || subgroup > 64) {
    return absl::FailedPreconditionError(absl::StrCat(
        ctx.description(), ": the deterministic LiDAR backward needs a subgroup size in [4, 64], not ",
        subgroup));
  }
  const SpecConstant subgroup_size[] = {{0, subgroup}};
  const PipelineSpec det[] = {
      {&k->blend_backward_det, "lidar_blend_backward_det", spirv::lidar_blend_backward_det, 9,
       sizeof(LidarBackwardPush) + 4, subgroup_size},
      {&k->det_rank_of, "lidar_det_rank_of", spirv::lidar_det_rank_of, 3, 0, {}},
      {&k->det_reduce, "lidar_det_reduce", spirv::lidar_det_reduce, 5, 12, {}},
  };
  absl::Status s = CreatePipelines(ctx, det);
  if (!s.ok()) k->blend_backward_det.reset();
  return s;
}

void RecordLidarBackward(Recorder& rec, const LidarKernels& k, const LidarFrameBuffers& f,
                         const BinningResult& bins, const LidarProjectPush& project,
                         const LidarBackwardPush& push, const LidarBackwardBuffers& bwd) {
  if (k.blend_backward == nullptr) {
    rec.Fail(absl::FailedPreconditionError(
        "vulkan LiDAR: the backward pass needs subgroup arithmetic operations"));
    return;
  }
  const VkDeviceSize n = project.n;
  if (n == 0) return;
  rec.Fill(*bwd.splat_grads, 0, n * kLidarSplatGradFloats * 4, 0);
  if (bwd.det_slots != nullptr) rec.Fill(*bwd.det_rank_of, 0, 2 * n * 4, 0xffffffffu);
  rec.Barrier();
  const uint32_t tiles_y = static_cast<uint32_t>(DivUp(push.beams, kTileSize));
  if (bwd.det_slots != nullptr) {
    // Slots per tile instance (every one written), the range order's inverse, then per Gaussian
    // its entries' slots in a fixed order: no atomics.
    const uint32_t slot_capacity = static_cast<uint32_t>(
        std::min<uint64_t>(bwd.det_slot_capacity, uint64_t{UINT32_MAX} / kLidarSplatGradFloats));
    struct DetPush {
      LidarBackwardPush blend;
      uint32_t slot_capacity;
    };
    rec.Dispatch(*k.blend_backward_det,
                 {f.ranges, bins.list, f.sorted_splats, bins.sorted_ids, f.ray_state, bwd.ray_grads,
                  bwd.det_slots, f.touched_sorted, f.rects},
                 DetPush{push, slot_capacity}, Grid{push.tiles_x, tiles_y});
    rec.DispatchIndirect(*k.det_rank_of, {bins.sorted_ids, bwd.counts, bwd.det_rank_of}, *bwd.args,
                         kArgsVThreads * kArgsSlotBytes);
    rec.Barrier();
    struct ReducePush {
      uint32_t n, slot_capacity, splat_capacity;
    };
    rec.Dispatch(*k.det_reduce,
                 {bwd.det_rank_of, f.touched_sorted, bwd.counts, bwd.det_slots, bwd.splat_grads},
                 ReducePush{project.n, slot_capacity, push.splat_capacity},
                 GridFor(DivUp(project.n, kWorkgroupSize)));
  } else {
    rec.Dispatch(*k.blend_backward,
                 {f.ranges, bins.list, f.sorted_splats, bins.sorted_ids, f.ray_state, bwd.ray_grads,
                  bwd.splat_grads},
                 push, Grid{push.tiles_x, tiles_y});
  }
  rec.Barrier();
  rec.Dispatch(*k.project_backward,
               {f.gauss, f.table, f.reflectance, bwd.splat_grads, bwd.param_grads, f.splats}, project,
               GridFor(DivUp(project.n, kWorkgroupSize)));
  rec.Barrier();
}

void UnpackLidarGrads(const float* pg, size_t n, LidarGaussianGrads* out) {
  out->means.resize(n * 3);
  out->log_scales.resize(n * 3);
  out->rotations.resize(n * 4);
  out->opacity_logits.resize(n);
  out->reflectance.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const float* p = pg + i * kLidarParamGradFloats;
    std::memcpy(&out->means[i * 3], p, 12);
    out->opacity_logits[i] = p[3];
    std::memcpy(&out->log_scales[i * 3], p + 4, 12);
    out->reflectance[i] = p[7];
    std::memcpy(&out->rotations[i * 4], p + 8, 16);
  }
}

}  // namespace streetsim::vulkan
