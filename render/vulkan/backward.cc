// The backward pass (shaders/blend_backward.glsl, shaders/project_backward.comp), recorded into
// one command buffer after the kept forward frame: zero the accumulators, blend backward (one
// workgroup per tile, float atomics per splat and lane), projection backward (one thread per
// visible Gaussian, indirect over V as counted by the forward). Deterministic mode replaces the
// atomics by one slot per tile instance (blend_backward_det) and a per-Gaussian sum of its slots
// in emit order (blend_backward_reduce): docs/rendering.md "Deterministic mode".
#include <algorithm>

#include "absl/strings/str_cat.h"
#include "render/vulkan/stages.h"
#include "streetsim_spirv.h"

namespace streetsim::vulkan {

absl::Status EnsureDeterministicKernels(const Context& ctx, Kernels* k) {
  if (k->blend_backward_det != nullptr) return absl::OkStatus();
  const uint32_t subgroup = ctx.subgroup().size;
  if (!ctx.has_subgroup_arithmetic()) {
    return absl::FailedPreconditionError(absl::StrCat(
        ctx.description(), ": the backward pass needs subgroup arithmetic operations"));
  }
  if (ctx.limits().maxComputeSharedMemorySize < kDetSharedBytes) {
    return absl::FailedPreconditionError(absl::StrCat(
        ctx.description(), ": the deterministic backward needs ", kDetSharedBytes,
        " bytes of compute shared memory, the device has ",
        ctx.limits().maxComputeSharedMemorySize));
  }
  // blend_backward.glsl sums at most 64 subgroups (unrolled).
  if (subgroup < 4 || subgroup > 64) {
    return absl::FailedPreconditionError(absl::StrCat(
        ctx.description(), ": the deterministic backward needs a subgroup size in [4, 64], not ",
        subgroup));
  }
  // Specialised for the subgroup size (constant subgroup count and shared-memory indices).
  const SpecConstant subgroup_size[] = {{0, subgroup}};
  const PipelineSpec det[] = {
      {&k->blend_backward_det, "blend_backward_det", spirv::blend_backward_det, 10, 32,
       subgroup_size},
      {&k->blend_backward_reduce, "blend_backward_reduce", spirv::blend_backward_reduce, 4, 4, {}},
  };
  absl::Status s = CreatePipelines(ctx, det);
  if (!s.ok()) k->blend_backward_det.reset();
  return s;
}

void RecordBackward(Recorder& rec, const Kernels& k, const SceneBuffers& scene,
                    const Buffer& ranges, const BinningResult& bins, const ImageBuffers& image,
                    const BlendParams& params, const Buffer& counts, const Buffer& args,
                    const ProjectPush& push, const BackwardBuffers& bwd) {
  if (k.blend_backward == nullptr) {
    rec.Fail(absl::FailedPreconditionError(
        "vulkan: the backward pass needs subgroup arithmetic operations"));
    return;
  }
  const VkDeviceSize n = push.n;
  rec.Fill(*bwd.splat_grads, 0, n * kSplatGradFloats * 4, 0);
  rec.Fill(*bwd.param_grads, 0, n * kParamGradFloats * 4, 0);
  for (int g = 0; g < kMaxShGroups; ++g) {
    if (bwd.sh_grad_bytes[g] > 0) rec.Fill(*bwd.sh_grads[g], 0, bwd.sh_grad_bytes[g], 0);
  }
  rec.Barrier();
  struct BlendPush {
    uint32_t width, height, tiles_x, rank_mask;
    float bg_r, bg_g, bg_b;
  };
  const BlendPush bp{params.width,        params.height,        params.tiles_x,
                     bins.rank_mask,      params.background[0], params.background[1],
                     params.background[2]};
  if (bwd.det_slots != nullptr) {
    struct DetPush {
      BlendPush blend;
      uint32_t slot_capacity;
    };
    const uint32_t slot_capacity = static_cast<uint32_t>(
        std::min<uint64_t>(bwd.det_slot_capacity, uint64_t{UINT32_MAX} / kDetSlotFloats));
    rec.Dispatch(*k.blend_backward_det,
                 {&ranges, bins.list, scene.sorted_splats, image.final_t, image.n_contrib,
                  bwd.pixel_grads, bwd.det_slots, bins.sorted_ids, scene.touched_sorted,
                  scene.rects},
                 DetPush{bp, slot_capacity}, Grid{params.tiles_x, params.tiles_y});
    rec.Barrier();
    rec.DispatchIndirect(*k.blend_backward_reduce,
                         {scene.touched_sorted, &counts, bwd.det_slots, bwd.splat_grads},
                         slot_capacity, args, kArgsVThreads * kArgsSlotBytes);
  } else {
    rec.Dispatch(*k.blend_backward,
                 {&ranges, bins.list, scene.sorted_splats, image.final_t, image.n_contrib,
                  bwd.pixel_grads, bwd.splat_grads},
                 bp, Grid{params.tiles_x, params.tiles_y});
  }
  rec.Barrier();
  rec.DispatchIndirect(*k.project_backward[push.sh_degree],
                       {scene.gauss, scene.sh[0], scene.sh[1], scene.sh[2], scene.sh[3],
                        bins.sorted_ids, &counts, bwd.splat_grads, bwd.param_grads,
                        bwd.sh_grads[0], bwd.sh_grads[1], bwd.sh_grads[2], bwd.sh_grads[3]},
                       push, args, kArgsVThreads * kArgsSlotBytes);
  rec.Barrier();
}

}  // namespace streetsim::vulkan
