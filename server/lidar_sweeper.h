// The server's LiDAR renderer: the cpu LidarRenderer, or the
// VulkanLidarRenderer when the camera engine runs on a Vulkan GPU (64x2048
// sweep of 500k Gaussians: 6.5 ms on an H100 vs 33 ms on 2 CPU cores,
// docs/benchmarks.md). On lavapipe the cpu renderer is ~7x faster than Vulkan,
// so a vulkan engine without a GPU keeps the LiDAR on the cpu.
#pragma once

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/engine.h"
#include "render/lidar/lidar_renderer.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::server {

class LidarSweeper {
public:
  virtual ~LidarSweeper() = default;
  virtual absl::Status Upload(const GaussianStore &store) = 0;
  // Only `change` differs from the last upload (a dynamic scene's next time); the default uploads
  // the whole store again.
  virtual absl::Status UpdateRows(const GaussianStore &store,
                                  const ParamsChange &change) {
    return Upload(store);
  }
  virtual absl::Status Render(const LidarModel &model,
                              const LidarSweepPose &sweep,
                              const LidarRenderOptions &options,
                              LidarRenderOutput *out) = 0;
  virtual std::string device_name() const = 0;
};

enum class LidarDevice {
  kFollowEngine, // Vulkan GPU when the engine is vulkan and a GPU exists, else
                 // cpu
  kCpu,
  kVulkanAnyDevice, // tests: the Vulkan renderer even on lavapipe
};

// FailedPrecondition when kVulkanAnyDevice finds no Vulkan device.
// kFollowEngine falls back to the cpu (with a warning) when the GPU renderer
// cannot be created.
absl::StatusOr<std::unique_ptr<LidarSweeper>>
CreateLidarSweeper(Backend engine_backend, LidarDevice device);

} // namespace streetsim::server
