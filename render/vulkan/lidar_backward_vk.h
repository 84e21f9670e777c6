// The vulkan LiDAR backward pass's stages (internal to VulkanLidarRenderer, docs/lidar.md "Vulkan",
// "Backward"): recorded into one command buffer after a sweep rendered with keep_for_backward,
// whose splats, tile lists, range order and per-ray state (final T, last contributor) stay on the
// device: zero the per-Gaussian accumulators, blend backward (one workgroup per tile, float
// atomics per splat and lane, shaders/lidar_blend_backward.glsl), projection backward (one thread
// per Gaussian, shaders/lidar_project_backward.comp).
#pragma once

#include <cstddef>
#include <cstdint>

#include "render/lidar/lidar_gradients.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/lidar_stages_vk.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

inline constexpr uint32_t kLidarSplatGradFloats = 8;   // lidar_blend_backward.glsl: GRAD_STRIDE
inline constexpr uint32_t kLidarParamGradFloats = 12;  // 3 vec4 per Gaussian (lidar_project_backward.comp)

// Mirrors shaders/lidar_blend_backward.glsl's push constants.
struct LidarBackwardPush {
  uint32_t columns, beams, tiles_x, rank_mask, splat_capacity;
};
static_assert(sizeof(LidarBackwardPush) == 20);

struct LidarBackwardBuffers {
  const Buffer* ray_grads;    // dL/d range_sum [P] | alpha [P] | intensity_sum [P]
  const Buffer* splat_grads;  // kLidarSplatGradFloats per Gaussian (zeroed here)
  const Buffer* param_grads;  // kLidarParamGradFloats per Gaussian (every one written)
  // Deterministic mode (null det_slots: float atomics): kLidarSplatGradFloats per tile instance
  // of the kept sweep (det_slot_capacity of them), a uint per entry (2 n) for the range order's
  // inverse, and the sweep's counts / args buffers (V, I, the per-rank grid).
  const Buffer* det_slots = nullptr;
  uint64_t det_slot_capacity = 0;
  const Buffer* det_rank_of = nullptr;
  const Buffer* counts = nullptr;
  const Buffer* args = nullptr;
};

// Builds k's deterministic-mode pipelines unless built: FailedPrecondition on a device that cannot
// run them (no subgroup arithmetic, a subgroup size outside [4, 64]).
absl::Status EnsureLidarDeterministicKernels(const Context& ctx, LidarKernels* k);

// The kept sweep's buffers f and binning bins; project: the sweep's projection push constants.
// Fails the recorder (FailedPrecondition) when the device has no blend backward. With
// bwd.det_slots the deterministic kernels replace the atomic blend backward (docs/lidar.md).
void RecordLidarBackward(Recorder& rec, const LidarKernels& k, const LidarFrameBuffers& f,
                         const BinningResult& bins, const LidarProjectPush& project,
                         const LidarBackwardPush& push, const LidarBackwardBuffers& bwd);

// param_grads (read back, n * kLidarParamGradFloats) into the store's layouts.
void UnpackLidarGrads(const float* param_grads, size_t n, LidarGaussianGrads* out);

}  // namespace streetsim::vulkan
