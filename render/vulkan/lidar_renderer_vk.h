// The LiDAR range-image renderer on the vulkan backend: the cpu LidarRenderer's rules
// (render/lidar/lidar_renderer.h, docs/lidar.md) as Vulkan compute shaders, one command buffer
// and one fence wait per sweep (projection, compaction, range sort, tile binning, blend and the
// return decision all on the device; indirect dispatches sized on the device).
//
// Same Upload / Render contract and LidarRenderOutput as the cpu renderer; LidarRenderOptions::kernel
// is ignored. Results agree with the cpu scalar reference within float tolerance (the projection
// uses the vectorised kernel's float beam map and polynomial atan2); the sampled drop uses the
// cpu's splitmix64 hash of (seed, ray), so drop decisions agree wherever alpha does.
//
// Rolling sweep (render/lidar/lidar_sweep.h): column c's pose interpolates the start and end poses
// at (c + 0.5) / columns, computed on the host in double (ColumnPoseTable) and rounded to float
// once; each Gaussian is projected with the middle column's pose to find its column u0, then
// projected with the pose of column clamp(floor(u0 + 0.5), 0, columns - 1) (its seam copy too).
// Equal start and end poses are the static render exactly.
//
// Training: Render with keep_for_backward, then Backward (render/vulkan/lidar_backward_vk.h).
#pragma once

#include <cstddef>
#include <memory>
#include <string>

#include <Eigen/Geometry>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/lidar/lidar_gradients.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "render/lidar/lidar_sweep.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

class VulkanLidarRenderer {
 public:
  // Device choice as CreateVulkanEngine (STREETSIM_VK_DEVICE, else by preference);
  // FailedPrecondition when no usable Vulkan device exists.
  static absl::StatusOr<std::unique_ptr<VulkanLidarRenderer>> Create(
      VulkanDevicePreference preference = VulkanDevicePreference::kLavapipe);
  ~VulkanLidarRenderer();
  VulkanLidarRenderer(const VulkanLidarRenderer&) = delete;
  VulkanLidarRenderer& operator=(const VulkanLidarRenderer&) = delete;

  // Validates the store (InvalidArgument when it fails Validate() or is too large for the device)
  // and copies it to device memory for the following sweeps. On error the previously uploaded
  // scene is dropped.
  absl::Status Upload(const GaussianStore& store);
  size_t uploaded_size() const;

  // Renders the uploaded scene from one pose (static sweep). InvalidArgument for an invalid model,
  // a non-finite or non-rigid pose, a reflectance array of the wrong size, or nothing uploaded.
  absl::Status Render(const LidarModel& model, const Eigen::Isometry3d& T_world_from_lidar,
                      const LidarRenderOptions& options, LidarRenderOutput* out);
  // Rolling sweep from the poses at the sweep's start and end.
  absl::Status Render(const LidarModel& model, const LidarSweepPose& sweep,
                      const LidarRenderOptions& options, LidarRenderOutput* out);
  // One-shot: Upload(store) then Render.
  absl::Status Render(const GaussianStore& store, const LidarModel& model,
                      const Eigen::Isometry3d& T_world_from_lidar, const LidarRenderOptions& options,
                      LidarRenderOutput* out);
  absl::Status Render(const GaussianStore& store, const LidarModel& model, const LidarSweepPose& sweep,
                      const LidarRenderOptions& options, LidarRenderOutput* out);

  // Gradients of the last Render, the cpu LidarRenderer::Backward's contract (lidar_gradients.h):
  // upstream per ray [beams * columns] (null = zero) -> dL/d(means, log-scales, raw quaternions,
  // opacity logits, reflectance in [0, 1]), zero for undrawn Gaussians. FailedPrecondition unless
  // the last Render had keep_for_backward and succeeded with no Upload since, or when the device
  // lacks subgroup arithmetic; InvalidArgument for a null grads. deterministic = true: fixed-order
  // sums instead of float atomics, identical bits run to run (ResourceExhausted when its 32 bytes
  // per tile instance exceed the device's storage buffer range).
  absl::Status Backward(const LidarUpstreamGrads& upstream, LidarGaussianGrads* grads,
                        bool deterministic = false);

  std::string device_name() const;
  int rerenders() const;  // sweeps recorded twice to grow a buffer whose estimate was exceeded

 private:
  struct Impl;
  explicit VulkanLidarRenderer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace streetsim
