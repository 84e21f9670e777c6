#include "render/engine.h"

#include "render/common/log.h"
#include "absl/strings/str_cat.h"
#include "render/cpu/cpu_engine.h"
#include "render/vulkan/vulkan_engine.h"

namespace streetsim {

absl::StatusOr<Backend> ParseBackend(std::string_view name) {
  if (name == "auto") return Backend::kAuto;
  if (name == "cpu") return Backend::kCpu;
  if (name == "vulkan") return Backend::kVulkan;
  return absl::InvalidArgumentError(
      absl::StrCat("unknown backend '", std::string(name), "' (expected auto, cpu or vulkan)"));
}

std::string_view BackendName(Backend backend) {
  switch (backend) {
    case Backend::kAuto: return "auto";
    case Backend::kCpu: return "cpu";
    case Backend::kVulkan: return "vulkan";
  }
  return "?";
}

absl::StatusOr<std::unique_ptr<Engine>> CreateEngine(Backend backend) {
  switch (backend) {
    case Backend::kCpu:
      return CreateCpuEngine();
    case Backend::kVulkan:
      // Explicit vulkan: lavapipe unless STREETSIM_VK_DEVICE names another device, so CI and a
      // developer's machine run the same driver.
      return CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
    case Backend::kAuto:
      // Lavapipe is 7-8x slower than the cpu backend on the same cores
      // (docs/benchmarks.md), so auto only takes Vulkan for a real GPU.
      if (HasVulkanGpu()) {
        absl::StatusOr<std::unique_ptr<Engine>> engine =
            CreateVulkanEngine(VulkanDevicePreference::kGpu);
        if (engine.ok()) return engine;
        LOG(WARNING) << "Vulkan GPU present but unusable, falling back to cpu: "
                     << engine.status();
      }
      return CreateCpuEngine();
  }
  return absl::InvalidArgumentError("bad backend");
}

}  // namespace streetsim
