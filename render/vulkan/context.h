// Vulkan instance + device + compute queue for the vulkan backend (internal).
//
// One Context per engine. It owns the instance, the chosen physical device, a logical device with
// one compute queue, a command pool, and (Debug builds) the validation debug messenger.
#pragma once

#include <vulkan/vulkan.h>

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "render/vulkan/vulkan_engine.h"

namespace streetsim::vulkan {

// Maps a VkResult to a Status: out-of-memory -> ResourceExhausted, anything else -> Internal.
absl::Status VkStatus(VkResult result, absl::string_view what);
const char* VkResultName(VkResult result);

#define STREETSIM_VK_RETURN_IF_ERROR(expr, what)                        \
  do {                                                                  \
    const VkResult streetsim_vk_result_ = (expr);                       \
    if (streetsim_vk_result_ != VK_SUCCESS) {                           \
      return ::streetsim::vulkan::VkStatus(streetsim_vk_result_, what); \
    }                                                                   \
  } while (false)

// Subgroup capabilities of the compute stage, from VkPhysicalDeviceSubgroupProperties.
struct SubgroupInfo {
  uint32_t size = 0;
  VkSubgroupFeatureFlags operations = 0;
  VkShaderStageFlags stages = 0;
};

// What the kernels need from a device; a device without it is rejected with FailedPrecondition.
inline constexpr VkSubgroupFeatureFlags kRequiredSubgroupOps =
    VK_SUBGROUP_FEATURE_BASIC_BIT | VK_SUBGROUP_FEATURE_VOTE_BIT | VK_SUBGROUP_FEATURE_BALLOT_BIT;
inline constexpr uint32_t kRequiredWorkgroupInvocations = 256;

// A VkInstance on its own (device listing needs no device).
class Instance {
 public:
  // FailedPrecondition when there is no loader/driver.
  static absl::StatusOr<std::unique_ptr<Instance>> Create(bool enable_validation);
  ~Instance();
  Instance(const Instance&) = delete;
  Instance& operator=(const Instance&) = delete;

  VkInstance handle() const { return instance_; }
  bool validation_enabled() const { return messenger_ != VK_NULL_HANDLE; }
  // Validation warnings/errors seen so far (0 when validation is off).
  int validation_messages() const { return validation_messages_.load(); }
  absl::StatusOr<std::vector<VkPhysicalDevice>> PhysicalDevices() const;

 private:
  Instance() = default;
  static VKAPI_ATTR VkBool32 VKAPI_CALL OnDebugMessage(
      VkDebugUtilsMessageSeverityFlagBitsEXT severity, VkDebugUtilsMessageTypeFlagsEXT types,
      const VkDebugUtilsMessengerCallbackDataEXT* data, void* user);

  VkInstance instance_ = VK_NULL_HANDLE;
  VkDebugUtilsMessengerEXT messenger_ = VK_NULL_HANDLE;
  std::atomic<int> validation_messages_{0};
};

VulkanDeviceInfo DescribeDevice(VkPhysicalDevice device);

class Context {
 public:
  static absl::StatusOr<std::unique_ptr<Context>> Create(VulkanDevicePreference preference);
  ~Context();
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;

  VkDevice device() const { return device_; }
  VkPhysicalDevice physical_device() const { return physical_device_; }
  VkQueue queue() const { return queue_; }
  uint32_t queue_family() const { return queue_family_; }
  VkCommandPool command_pool() const { return command_pool_; }
  const VkPhysicalDeviceProperties& properties() const { return properties_; }
  const VkPhysicalDeviceLimits& limits() const { return properties_.limits; }
  const SubgroupInfo& subgroup() const { return subgroup_; }
  // VK_EXT_shader_atomic_float's shaderBufferFloat32AtomicAdd, enabled at device creation when
  // supported (the backward's float atomics; else a compare-and-swap loop).
  bool has_float_atomic_add() const { return float_atomic_add_; }
  // Subgroup arithmetic (subgroupAdd/Max): needed by the backward pass only.
  bool has_subgroup_arithmetic() const {
    return (subgroup_.operations & VK_SUBGROUP_FEATURE_ARITHMETIC_BIT) != 0;
  }
  bool is_cpu() const { return properties_.deviceType == VK_PHYSICAL_DEVICE_TYPE_CPU; }
  // Timestamps are usable when the queue reports valid bits; period converts ticks to ns.
  bool has_timestamps() const { return timestamp_valid_bits_ > 0; }
  uint32_t timestamp_valid_bits() const { return timestamp_valid_bits_; }
  double timestamp_period_ns() const { return properties_.limits.timestampPeriod; }
  int validation_messages() const { return instance_->validation_messages(); }
  std::string description() const;

  // Picks a memory type with all `required` flags, preferring one that also has `preferred`.
  absl::StatusOr<uint32_t> FindMemoryType(uint32_t type_bits, VkMemoryPropertyFlags required,
                                          VkMemoryPropertyFlags preferred) const;

  // Records with `record` into a fresh command buffer, submits it and waits (uploads, tests).
  absl::Status SubmitAndWait(const std::function<void(VkCommandBuffer)>& record) const;

 private:
  Context() = default;

  std::unique_ptr<Instance> instance_;
  VkPhysicalDevice physical_device_ = VK_NULL_HANDLE;
  VkDevice device_ = VK_NULL_HANDLE;
  VkQueue queue_ = VK_NULL_HANDLE;
  uint32_t queue_family_ = 0;
  VkCommandPool command_pool_ = VK_NULL_HANDLE;
  VkPhysicalDeviceProperties properties_{};
  VkPhysicalDeviceMemoryProperties memory_properties_{};
  SubgroupInfo subgroup_;
  bool float_atomic_add_ = false;
  uint32_t timestamp_valid_bits_ = 0;
};

}  // namespace streetsim::vulkan
