// The backward pass (shaders/blend_backward.glsl, shaders/project_backward.comp), recorded into
// one command buffer after the kept forward frame: zero the accumulators, blend backward (one
// workgroup per tile, float atomics per splat and lane), projection backward (one thread per
// visible Gaussian, indirect over V as counted by the forward).
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

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
  rec.Dispatch(*k.blend_backward,
               {&ranges, bins.list, scene.sorted_splats, image.final_t, image.n_contrib,
                bwd.pixel_grads, bwd.splat_grads},
               bp, Grid{params.tiles_x, params.tiles_y});
  rec.Barrier();
  rec.DispatchIndirect(*k.project_backward[push.sh_degree],
                       {scene.gauss, scene.sh[0], scene.sh[1], scene.sh[2], scene.sh[3],
                        bins.sorted_ids, &counts, bwd.splat_grads, bwd.param_grads,
                        bwd.sh_grads[0], bwd.sh_grads[1], bwd.sh_grads[2], bwd.sh_grads[3]},
                       push, args, kArgsVThreads * kArgsSlotBytes);
  rec.Barrier();
}

}  // namespace streetsim::vulkan
