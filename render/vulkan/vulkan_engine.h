// The vulkan backend: the 3DGS forward pass as Vulkan compute shaders (render/engine.h).
//
// Runs on any Vulkan 1.2 device with compute subgroups (basic, vote, ballot); Mesa lavapipe is the
// reference device. A frame is one command buffer and one submit: projection, visibility
// compaction, depth sort, tile binning, tile sort, tile ranges and blending, with every
// data-dependent dispatch size computed on the device (indirect dispatch).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"

namespace streetsim {

struct VulkanDeviceInfo {
  std::string name;
  bool is_cpu;
  uint32_t subgroup_size;
};

// Lists devices (empty vector if no loader/driver). Never crashes when libvulkan has no ICD.
std::vector<VulkanDeviceInfo> ListVulkanDevices();

// True if a non-CPU Vulkan device exists (used by --backend auto).
bool HasVulkanGpu();

enum class VulkanDevicePreference { kLavapipe, kGpu };

// Device choice: STREETSIM_VK_DEVICE (index or case-insensitive name substring) when set; else
// kLavapipe -> a CPU-type device if any, else the first device; kGpu -> first discrete, then
// integrated GPU, else CPU. Clear error (FailedPrecondition) naming what was found when no
// Vulkan driver / no device / no compute queue / missing required features.
absl::StatusOr<std::unique_ptr<Engine>> CreateVulkanEngine(VulkanDevicePreference pref);

}  // namespace streetsim
