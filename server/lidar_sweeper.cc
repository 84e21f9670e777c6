#include "server/lidar_sweeper.h"

#include "render/common/log.h"
#include "render/vulkan/lidar_renderer_vk.h"
#include "render/vulkan/vulkan_engine.h"

namespace streetsim::server {
namespace {

class CpuSweeper : public LidarSweeper {
public:
  absl::Status Upload(const GaussianStore &store) override {
    return renderer_.Upload(store);
  }
  absl::Status UpdateRows(const GaussianStore &store,
                          const ParamsChange &change) override {
    return renderer_.UpdateRows(store, change);
  }
  absl::Status Render(const LidarModel &model, const LidarSweepPose &sweep,
                      const LidarRenderOptions &options,
                      LidarRenderOutput *out) override {
    return renderer_.Render(model, sweep, options, out);
  }
  std::string device_name() const override {
    return std::string("cpu (") + LidarRenderer::SimdIsa() + ")";
  }

private:
  LidarRenderer renderer_;
};

class VulkanSweeper : public LidarSweeper {
public:
  explicit VulkanSweeper(std::unique_ptr<VulkanLidarRenderer> renderer)
      : renderer_(std::move(renderer)) {}
  absl::Status Upload(const GaussianStore &store) override {
    return renderer_->Upload(store);
  }
  absl::Status Render(const LidarModel &model, const LidarSweepPose &sweep,
                      const LidarRenderOptions &options,
                      LidarRenderOutput *out) override {
    return renderer_->Render(model, sweep, options, out);
  }
  std::string device_name() const override { return renderer_->device_name(); }

private:
  std::unique_ptr<VulkanLidarRenderer> renderer_;
};

} // namespace

absl::StatusOr<std::unique_ptr<LidarSweeper>>
CreateLidarSweeper(Backend engine_backend, LidarDevice device) {
  if (device == LidarDevice::kVulkanAnyDevice) {
    absl::StatusOr<std::unique_ptr<VulkanLidarRenderer>> vk =
        VulkanLidarRenderer::Create(VulkanDevicePreference::kLavapipe);
    if (!vk.ok())
      return vk.status();
    return std::unique_ptr<LidarSweeper>(
        std::make_unique<VulkanSweeper>(std::move(*vk)));
  }
  if (device == LidarDevice::kFollowEngine &&
      engine_backend == Backend::kVulkan && HasVulkanGpu()) {
    absl::StatusOr<std::unique_ptr<VulkanLidarRenderer>> vk =
        VulkanLidarRenderer::Create(VulkanDevicePreference::kGpu);
    if (vk.ok())
      return std::unique_ptr<LidarSweeper>(
          std::make_unique<VulkanSweeper>(std::move(*vk)));
    LOG(WARNING) << "LiDAR on the Vulkan GPU unavailable, sweeping on the cpu: "
                 << vk.status();
  }
  return std::unique_ptr<LidarSweeper>(std::make_unique<CpuSweeper>());
}

} // namespace streetsim::server
