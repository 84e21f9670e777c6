// Stage h: per-tile front-to-back blending (shaders/blend.comp), one workgroup per 16x16 tile.
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

void RecordBlend(Recorder& rec, const Kernels& k, const Buffer& ranges, const BinningResult& bins,
                 const Buffer& sorted_splats, const ImageBuffers& image,
                 const BlendParams& params) {
  struct BlendPush {
    uint32_t width, height, tiles_x, rank_mask;
    float bg_r, bg_g, bg_b;
  };
  const BlendPush push{params.width,        params.height,        params.tiles_x,
                       bins.rank_mask,      params.background[0], params.background[1],
                       params.background[2]};
  // tiles_x, tiles_y <= 256 (kMaxImageSide / 16): always within maxComputeWorkGroupCount.
  rec.Dispatch(*k.blend,
               {&ranges, bins.list, &sorted_splats, image.rgb, image.depth, image.alpha,
                image.final_t, image.n_contrib},
               push, Grid{params.tiles_x, params.tiles_y});
  rec.Barrier();
}

}  // namespace streetsim::vulkan
