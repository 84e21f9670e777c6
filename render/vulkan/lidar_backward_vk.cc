// The vulkan LiDAR backward pass's stages (lidar_backward_vk.h).
#include "render/vulkan/lidar_backward_vk.h"

#include <cstring>

#include "absl/status/status.h"

namespace streetsim::vulkan {

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
  rec.Barrier();
  const uint32_t tiles_y = static_cast<uint32_t>(DivUp(push.beams, kTileSize));
  rec.Dispatch(*k.blend_backward,
               {f.ranges, bins.list, f.sorted_splats, bins.sorted_ids, f.ray_state, bwd.ray_grads,
                bwd.splat_grads},
               push, Grid{push.tiles_x, tiles_y});
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
