#include "render/vulkan/context.h"

#include <algorithm>
#include <cctype>
#include <cstdlib>
#include <cstring>
#include <optional>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "render/common/log.h"

namespace streetsim::vulkan {
namespace {

constexpr const char* kValidationLayer = "VK_LAYER_KHRONOS_validation";

bool ValidationRequested() {
#ifdef STREETSIM_VK_VALIDATION
  return true;
#else
  // Release builds can opt in at run time, e.g. to check a new shader.
  const char* env = std::getenv("STREETSIM_VK_VALIDATION");
  return env != nullptr && std::string_view(env) == "1";
#endif
}

bool HasInstanceLayer(const char* name) {
  uint32_t count = 0;
  if (vkEnumerateInstanceLayerProperties(&count, nullptr) != VK_SUCCESS) return false;
  std::vector<VkLayerProperties> layers(count);
  if (vkEnumerateInstanceLayerProperties(&count, layers.data()) != VK_SUCCESS) return false;
  for (const auto& layer : layers) {
    if (std::strcmp(layer.layerName, name) == 0) return true;
  }
  return false;
}

bool HasInstanceExtension(const char* name) {
  uint32_t count = 0;
  if (vkEnumerateInstanceExtensionProperties(nullptr, &count, nullptr) != VK_SUCCESS) return false;
  std::vector<VkExtensionProperties> exts(count);
  if (vkEnumerateInstanceExtensionProperties(nullptr, &count, exts.data()) != VK_SUCCESS) {
    return false;
  }
  for (const auto& ext : exts) {
    if (std::strcmp(ext.extensionName, name) == 0) return true;
  }
  return false;
}

bool HasDeviceExtension(VkPhysicalDevice device, const char* name) {
  uint32_t count = 0;
  if (vkEnumerateDeviceExtensionProperties(device, nullptr, &count, nullptr) != VK_SUCCESS) {
    return false;
  }
  std::vector<VkExtensionProperties> exts(count);
  if (vkEnumerateDeviceExtensionProperties(device, nullptr, &count, exts.data()) != VK_SUCCESS) {
    return false;
  }
  for (const VkExtensionProperties& ext : exts) {
    if (std::strcmp(ext.extensionName, name) == 0) return true;
  }
  return false;
}

SubgroupInfo QuerySubgroup(VkPhysicalDevice device) {
  VkPhysicalDeviceSubgroupProperties subgroup{
      VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_SUBGROUP_PROPERTIES};
  VkPhysicalDeviceProperties2 props2{VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_PROPERTIES_2};
  props2.pNext = &subgroup;
  vkGetPhysicalDeviceProperties2(device, &props2);
  return SubgroupInfo{subgroup.subgroupSize, subgroup.supportedOperations,
                      subgroup.supportedStages};
}

// The queue family used for compute: prefer one with timestamps.
std::optional<uint32_t> PickComputeQueue(VkPhysicalDevice device, uint32_t* timestamp_bits) {
  uint32_t count = 0;
  vkGetPhysicalDeviceQueueFamilyProperties(device, &count, nullptr);
  std::vector<VkQueueFamilyProperties> families(count);
  vkGetPhysicalDeviceQueueFamilyProperties(device, &count, families.data());
  std::optional<uint32_t> best;
  for (uint32_t i = 0; i < count; ++i) {
    if (!(families[i].queueFlags & VK_QUEUE_COMPUTE_BIT) || families[i].queueCount == 0) continue;
    if (!best || (families[i].timestampValidBits > 0 && families[*best].timestampValidBits == 0)) {
      best = i;
    }
  }
  if (best && timestamp_bits != nullptr) *timestamp_bits = families[*best].timestampValidBits;
  return best;
}

std::string DeviceTypeName(VkPhysicalDeviceType type) {
  switch (type) {
    case VK_PHYSICAL_DEVICE_TYPE_DISCRETE_GPU:
      return "discrete";
    case VK_PHYSICAL_DEVICE_TYPE_INTEGRATED_GPU:
      return "integrated";
    case VK_PHYSICAL_DEVICE_TYPE_VIRTUAL_GPU:
      return "virtual";
    case VK_PHYSICAL_DEVICE_TYPE_CPU:
      return "cpu";
    default:
      return "other";
  }
}

// Empty when the device can run the kernels, else what it lacks.
std::string MissingRequirements(VkPhysicalDevice device) {
  VkPhysicalDeviceProperties props;
  vkGetPhysicalDeviceProperties(device, &props);
  std::vector<std::string> missing;
  if (props.apiVersion < VK_API_VERSION_1_2) missing.push_back("Vulkan 1.2");
  if (!PickComputeQueue(device, nullptr)) missing.push_back("a compute queue");
  const SubgroupInfo sg = QuerySubgroup(device);
  if (!(sg.stages & VK_SHADER_STAGE_COMPUTE_BIT)) missing.push_back("subgroups in compute shaders");
  if ((sg.operations & kRequiredSubgroupOps) != kRequiredSubgroupOps) {
    missing.push_back("subgroup basic+vote+ballot operations");
  }
  if (sg.size == 0) missing.push_back("a subgroup size");
  if (props.limits.maxComputeWorkGroupInvocations < kRequiredWorkgroupInvocations ||
      props.limits.maxComputeWorkGroupSize[0] < kRequiredWorkgroupInvocations) {
    missing.push_back("256-invocation workgroups");
  }
  return absl::StrJoin(missing, ", ");
}

std::string ListForError(const std::vector<VkPhysicalDevice>& devices) {
  std::vector<std::string> parts;
  for (size_t i = 0; i < devices.size(); ++i) {
    VkPhysicalDeviceProperties props;
    vkGetPhysicalDeviceProperties(devices[i], &props);
    parts.push_back(
        absl::StrCat("[", i, "] ", props.deviceName, " (", DeviceTypeName(props.deviceType), ")"));
  }
  return parts.empty() ? "no devices" : absl::StrJoin(parts, ", ");
}

absl::StatusOr<VkPhysicalDevice> PickDevice(const std::vector<VkPhysicalDevice>& devices,
                                            VulkanDevicePreference preference) {
  if (devices.empty()) {
    return absl::FailedPreconditionError(
        "vulkan: the Vulkan loader found no physical devices (no ICD installed? for lavapipe "
        "install mesa-vulkan-drivers)");
  }
  if (const char* env = std::getenv("STREETSIM_VK_DEVICE"); env != nullptr && *env != '\0') {
    const std::string wanted(env);
    std::optional<size_t> chosen;
    uint32_t index = 0;
    if (absl::SimpleAtoi(wanted, &index)) {
      if (index < devices.size()) chosen = index;
    } else {
      for (size_t i = 0; i < devices.size() && !chosen; ++i) {
        VkPhysicalDeviceProperties props;
        vkGetPhysicalDeviceProperties(devices[i], &props);
        if (absl::StrContains(absl::AsciiStrToLower(props.deviceName),
                              absl::AsciiStrToLower(wanted))) {
          chosen = i;
        }
      }
    }
    if (!chosen) {
      return absl::FailedPreconditionError(
          absl::StrCat("vulkan: STREETSIM_VK_DEVICE='", wanted,
                       "' matches no Vulkan device; found: ", ListForError(devices)));
    }
    const std::string missing = MissingRequirements(devices[*chosen]);
    if (!missing.empty()) {
      return absl::FailedPreconditionError(absl::StrCat(
          "vulkan: device [", *chosen, "] chosen by STREETSIM_VK_DEVICE lacks ", missing));
    }
    return devices[*chosen];
  }

  std::vector<VkPhysicalDevice> usable;
  std::vector<std::string> problems;
  for (size_t i = 0; i < devices.size(); ++i) {
    const std::string missing = MissingRequirements(devices[i]);
    if (missing.empty()) {
      usable.push_back(devices[i]);
    } else {
      VkPhysicalDeviceProperties props;
      vkGetPhysicalDeviceProperties(devices[i], &props);
      problems.push_back(absl::StrCat(props.deviceName, " lacks ", missing));
    }
  }
  if (usable.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat("vulkan: no usable device: ", absl::StrJoin(problems, "; ")));
  }
  auto first_of = [&](VkPhysicalDeviceType type) -> std::optional<VkPhysicalDevice> {
    for (VkPhysicalDevice d : usable) {
      VkPhysicalDeviceProperties props;
      vkGetPhysicalDeviceProperties(d, &props);
      if (props.deviceType == type) return d;
    }
    return std::nullopt;
  };
  if (preference == VulkanDevicePreference::kLavapipe) {
    return first_of(VK_PHYSICAL_DEVICE_TYPE_CPU).value_or(usable.front());
  }
  for (VkPhysicalDeviceType type :
       {VK_PHYSICAL_DEVICE_TYPE_DISCRETE_GPU, VK_PHYSICAL_DEVICE_TYPE_INTEGRATED_GPU,
        VK_PHYSICAL_DEVICE_TYPE_CPU}) {
    if (auto d = first_of(type)) return *d;
  }
  return usable.front();
}

}  // namespace

const char* VkResultName(VkResult result) {
  switch (result) {
    case VK_SUCCESS:
      return "VK_SUCCESS";
    case VK_NOT_READY:
      return "VK_NOT_READY";
    case VK_TIMEOUT:
      return "VK_TIMEOUT";
    case VK_INCOMPLETE:
      return "VK_INCOMPLETE";
    case VK_ERROR_OUT_OF_HOST_MEMORY:
      return "VK_ERROR_OUT_OF_HOST_MEMORY";
    case VK_ERROR_OUT_OF_DEVICE_MEMORY:
      return "VK_ERROR_OUT_OF_DEVICE_MEMORY";
    case VK_ERROR_INITIALIZATION_FAILED:
      return "VK_ERROR_INITIALIZATION_FAILED";
    case VK_ERROR_DEVICE_LOST:
      return "VK_ERROR_DEVICE_LOST";
    case VK_ERROR_MEMORY_MAP_FAILED:
      return "VK_ERROR_MEMORY_MAP_FAILED";
    case VK_ERROR_LAYER_NOT_PRESENT:
      return "VK_ERROR_LAYER_NOT_PRESENT";
    case VK_ERROR_EXTENSION_NOT_PRESENT:
      return "VK_ERROR_EXTENSION_NOT_PRESENT";
    case VK_ERROR_FEATURE_NOT_PRESENT:
      return "VK_ERROR_FEATURE_NOT_PRESENT";
    case VK_ERROR_INCOMPATIBLE_DRIVER:
      return "VK_ERROR_INCOMPATIBLE_DRIVER";
    case VK_ERROR_TOO_MANY_OBJECTS:
      return "VK_ERROR_TOO_MANY_OBJECTS";
    case VK_ERROR_OUT_OF_POOL_MEMORY:
      return "VK_ERROR_OUT_OF_POOL_MEMORY";
    default:
      return "VkResult";
  }
}

absl::Status VkStatus(VkResult result, absl::string_view what) {
  if (result == VK_SUCCESS) return absl::OkStatus();
  const std::string message = absl::StrCat("vulkan: ", what, " failed: ", VkResultName(result),
                                           " (", static_cast<int>(result), ")");
  if (result == VK_ERROR_OUT_OF_HOST_MEMORY || result == VK_ERROR_OUT_OF_DEVICE_MEMORY) {
    return absl::ResourceExhaustedError(message);
  }
  if (result == VK_ERROR_INCOMPATIBLE_DRIVER || result == VK_ERROR_INITIALIZATION_FAILED ||
      result == VK_ERROR_LAYER_NOT_PRESENT || result == VK_ERROR_EXTENSION_NOT_PRESENT ||
      result == VK_ERROR_FEATURE_NOT_PRESENT) {
    return absl::FailedPreconditionError(message);
  }
  return absl::InternalError(message);
}

// ---------------------------------------------------------------------------------------------

absl::StatusOr<std::unique_ptr<Instance>> Instance::Create(bool enable_validation) {
  auto instance = std::unique_ptr<Instance>(new Instance());
  VkApplicationInfo app{VK_STRUCTURE_TYPE_APPLICATION_INFO};
  app.pApplicationName = "streetsim";
  app.pEngineName = "streetsim";
  app.apiVersion = VK_API_VERSION_1_2;

  std::vector<const char*> layers;
  std::vector<const char*> extensions;
  const bool validation = enable_validation && HasInstanceLayer(kValidationLayer) &&
                          HasInstanceExtension(VK_EXT_DEBUG_UTILS_EXTENSION_NAME);
  if (enable_validation && !validation) {
    LOG(WARNING) << "vulkan: validation requested but " << kValidationLayer
                 << " / VK_EXT_debug_utils is not installed";
  }
  if (validation) {
    layers.push_back(kValidationLayer);
    extensions.push_back(VK_EXT_DEBUG_UTILS_EXTENSION_NAME);
  }
  VkDebugUtilsMessengerCreateInfoEXT messenger_info{
      VK_STRUCTURE_TYPE_DEBUG_UTILS_MESSENGER_CREATE_INFO_EXT};
  messenger_info.messageSeverity = VK_DEBUG_UTILS_MESSAGE_SEVERITY_WARNING_BIT_EXT |
                                   VK_DEBUG_UTILS_MESSAGE_SEVERITY_ERROR_BIT_EXT;
  messenger_info.messageType = VK_DEBUG_UTILS_MESSAGE_TYPE_GENERAL_BIT_EXT |
                               VK_DEBUG_UTILS_MESSAGE_TYPE_VALIDATION_BIT_EXT |
                               VK_DEBUG_UTILS_MESSAGE_TYPE_PERFORMANCE_BIT_EXT;
  messenger_info.pfnUserCallback = &Instance::OnDebugMessage;
  messenger_info.pUserData = instance.get();

  VkInstanceCreateInfo info{VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO};
  info.pApplicationInfo = &app;
  info.enabledLayerCount = static_cast<uint32_t>(layers.size());
  info.ppEnabledLayerNames = layers.data();
  info.enabledExtensionCount = static_cast<uint32_t>(extensions.size());
  info.ppEnabledExtensionNames = extensions.data();
  // Chained so that instance creation itself is validated too.
  if (validation) info.pNext = &messenger_info;
  const VkResult result = vkCreateInstance(&info, nullptr, &instance->instance_);
  if (result != VK_SUCCESS) {
    instance->instance_ = VK_NULL_HANDLE;
    return absl::FailedPreconditionError(
        absl::StrCat("vulkan: vkCreateInstance failed (", VkResultName(result),
                     "): no Vulkan driver available (for lavapipe install mesa-vulkan-drivers)"));
  }
  if (validation) {
    auto create = reinterpret_cast<PFN_vkCreateDebugUtilsMessengerEXT>(
        vkGetInstanceProcAddr(instance->instance_, "vkCreateDebugUtilsMessengerEXT"));
    if (create != nullptr) {
      STREETSIM_VK_RETURN_IF_ERROR(
          create(instance->instance_, &messenger_info, nullptr, &instance->messenger_),
          "vkCreateDebugUtilsMessengerEXT");
    }
  }
  return instance;
}

Instance::~Instance() {
  if (messenger_ != VK_NULL_HANDLE) {
    auto destroy = reinterpret_cast<PFN_vkDestroyDebugUtilsMessengerEXT>(
        vkGetInstanceProcAddr(instance_, "vkDestroyDebugUtilsMessengerEXT"));
    if (destroy != nullptr) destroy(instance_, messenger_, nullptr);
  }
  if (instance_ != VK_NULL_HANDLE) vkDestroyInstance(instance_, nullptr);
}

VKAPI_ATTR VkBool32 VKAPI_CALL Instance::OnDebugMessage(
    VkDebugUtilsMessageSeverityFlagBitsEXT severity, VkDebugUtilsMessageTypeFlagsEXT types,
    const VkDebugUtilsMessengerCallbackDataEXT* data, void* user) {
  if (user != nullptr) ++static_cast<Instance*>(user)->validation_messages_;
  LOG(WARNING) << "vulkan validation: " << (data && data->pMessage ? data->pMessage : "?");
  return VK_FALSE;
}

absl::StatusOr<std::vector<VkPhysicalDevice>> Instance::PhysicalDevices() const {
  uint32_t count = 0;
  STREETSIM_VK_RETURN_IF_ERROR(vkEnumeratePhysicalDevices(instance_, &count, nullptr),
                               "vkEnumeratePhysicalDevices");
  std::vector<VkPhysicalDevice> devices(count);
  if (count > 0) {
    VkResult r = vkEnumeratePhysicalDevices(instance_, &count, devices.data());
    if (r != VK_SUCCESS && r != VK_INCOMPLETE) return VkStatus(r, "vkEnumeratePhysicalDevices");
    devices.resize(count);
  }
  return devices;
}

VulkanDeviceInfo DescribeDevice(VkPhysicalDevice device) {
  VkPhysicalDeviceProperties props;
  vkGetPhysicalDeviceProperties(device, &props);
  return VulkanDeviceInfo{props.deviceName, props.deviceType == VK_PHYSICAL_DEVICE_TYPE_CPU,
                          QuerySubgroup(device).size};
}

// ---------------------------------------------------------------------------------------------

absl::StatusOr<std::unique_ptr<Context>> Context::Create(VulkanDevicePreference preference) {
  auto ctx = std::unique_ptr<Context>(new Context());
  auto instance = Instance::Create(ValidationRequested());
  if (!instance.ok()) return instance.status();
  ctx->instance_ = *std::move(instance);
  auto devices = ctx->instance_->PhysicalDevices();
  if (!devices.ok()) return devices.status();
  auto device = PickDevice(*devices, preference);
  if (!device.ok()) return device.status();
  ctx->physical_device_ = *device;
  vkGetPhysicalDeviceProperties(ctx->physical_device_, &ctx->properties_);
  vkGetPhysicalDeviceMemoryProperties(ctx->physical_device_, &ctx->memory_properties_);
  ctx->subgroup_ = QuerySubgroup(ctx->physical_device_);
  ctx->queue_family_ = *PickComputeQueue(ctx->physical_device_, &ctx->timestamp_valid_bits_);
  // timestampPeriod 0 would make every stage time 0; treat it as "no timestamps".
  if (ctx->properties_.limits.timestampPeriod <= 0) ctx->timestamp_valid_bits_ = 0;

  const float priority = 1.0f;
  VkDeviceQueueCreateInfo queue_info{VK_STRUCTURE_TYPE_DEVICE_QUEUE_CREATE_INFO};
  queue_info.queueFamilyIndex = ctx->queue_family_;
  queue_info.queueCount = 1;
  queue_info.pQueuePriorities = &priority;
  VkDeviceCreateInfo device_info{VK_STRUCTURE_TYPE_DEVICE_CREATE_INFO};
  device_info.queueCreateInfoCount = 1;
  device_info.pQueueCreateInfos = &queue_info;
  // Float atomic add on storage buffers (the backward's gradient sums), when offered.
  VkPhysicalDeviceShaderAtomicFloatFeaturesEXT atomic_float{
      VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_SHADER_ATOMIC_FLOAT_FEATURES_EXT};
  const char* atomic_float_ext = VK_EXT_SHADER_ATOMIC_FLOAT_EXTENSION_NAME;
  if (HasDeviceExtension(ctx->physical_device_, atomic_float_ext) &&
      std::getenv("STREETSIM_VK_NO_FLOAT_ATOMICS") == nullptr) {
    VkPhysicalDeviceFeatures2 features2{VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_FEATURES_2};
    features2.pNext = &atomic_float;
    vkGetPhysicalDeviceFeatures2(ctx->physical_device_, &features2);
    if (atomic_float.shaderBufferFloat32AtomicAdd) {
      VkPhysicalDeviceShaderAtomicFloatFeaturesEXT wanted{
          VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_SHADER_ATOMIC_FLOAT_FEATURES_EXT};
      wanted.shaderBufferFloat32AtomicAdd = VK_TRUE;
      atomic_float = wanted;
      device_info.pNext = &atomic_float;
      device_info.enabledExtensionCount = 1;
      device_info.ppEnabledExtensionNames = &atomic_float_ext;
      ctx->float_atomic_add_ = true;
    }
  }
  STREETSIM_VK_RETURN_IF_ERROR(
      vkCreateDevice(ctx->physical_device_, &device_info, nullptr, &ctx->device_),
      "vkCreateDevice");
  vkGetDeviceQueue(ctx->device_, ctx->queue_family_, 0, &ctx->queue_);

  VkCommandPoolCreateInfo pool_info{VK_STRUCTURE_TYPE_COMMAND_POOL_CREATE_INFO};
  pool_info.flags = VK_COMMAND_POOL_CREATE_RESET_COMMAND_BUFFER_BIT;
  pool_info.queueFamilyIndex = ctx->queue_family_;
  STREETSIM_VK_RETURN_IF_ERROR(
      vkCreateCommandPool(ctx->device_, &pool_info, nullptr, &ctx->command_pool_),
      "vkCreateCommandPool");
  LOG(INFO) << "vulkan: using " << ctx->description();
  return ctx;
}

Context::~Context() {
  if (device_ != VK_NULL_HANDLE) {
    vkDeviceWaitIdle(device_);
    if (command_pool_ != VK_NULL_HANDLE) vkDestroyCommandPool(device_, command_pool_, nullptr);
    vkDestroyDevice(device_, nullptr);
  }
}

std::string Context::description() const {
  return absl::StrCat("vulkan: ", properties_.deviceName, " (",
                      DeviceTypeName(properties_.deviceType), ", subgroup ", subgroup_.size,
                      float_atomic_add_ ? "" : ", no float atomics",
                      instance_->validation_enabled() ? ", validation" : "", ")");
}

absl::StatusOr<uint32_t> Context::FindMemoryType(uint32_t type_bits, VkMemoryPropertyFlags required,
                                                 VkMemoryPropertyFlags preferred) const {
  std::optional<uint32_t> fallback;
  for (uint32_t i = 0; i < memory_properties_.memoryTypeCount; ++i) {
    if (!(type_bits & (1u << i))) continue;
    const VkMemoryPropertyFlags flags = memory_properties_.memoryTypes[i].propertyFlags;
    if ((flags & required) != required) continue;
    if ((flags & preferred) == preferred) return i;
    if (!fallback) fallback = i;
  }
  if (fallback) return *fallback;
  return absl::FailedPreconditionError(
      absl::StrCat("vulkan: no memory type with flags ", required));
}

absl::Status Context::SubmitAndWait(const std::function<void(VkCommandBuffer)>& record) const {
  VkCommandBufferAllocateInfo alloc{VK_STRUCTURE_TYPE_COMMAND_BUFFER_ALLOCATE_INFO};
  alloc.commandPool = command_pool_;
  alloc.level = VK_COMMAND_BUFFER_LEVEL_PRIMARY;
  alloc.commandBufferCount = 1;
  VkCommandBuffer cmd = VK_NULL_HANDLE;
  STREETSIM_VK_RETURN_IF_ERROR(vkAllocateCommandBuffers(device_, &alloc, &cmd),
                               "vkAllocateCommandBuffers");
  VkFence fence = VK_NULL_HANDLE;
  auto cleanup = [&] {
    if (fence != VK_NULL_HANDLE) vkDestroyFence(device_, fence, nullptr);
    vkFreeCommandBuffers(device_, command_pool_, 1, &cmd);
  };
  VkCommandBufferBeginInfo begin{VK_STRUCTURE_TYPE_COMMAND_BUFFER_BEGIN_INFO};
  begin.flags = VK_COMMAND_BUFFER_USAGE_ONE_TIME_SUBMIT_BIT;
  VkResult r = vkBeginCommandBuffer(cmd, &begin);
  if (r == VK_SUCCESS) {
    record(cmd);
    r = vkEndCommandBuffer(cmd);
  }
  VkFenceCreateInfo fence_info{VK_STRUCTURE_TYPE_FENCE_CREATE_INFO};
  if (r == VK_SUCCESS) r = vkCreateFence(device_, &fence_info, nullptr, &fence);
  if (r == VK_SUCCESS) {
    VkSubmitInfo submit{VK_STRUCTURE_TYPE_SUBMIT_INFO};
    submit.commandBufferCount = 1;
    submit.pCommandBuffers = &cmd;
    r = vkQueueSubmit(queue_, 1, &submit, fence);
  }
  if (r == VK_SUCCESS) r = vkWaitForFences(device_, 1, &fence, VK_TRUE, UINT64_MAX);
  cleanup();
  return VkStatus(r, "one-shot submit");
}

}  // namespace streetsim::vulkan

// ---------------------------------------------------------------------------------------------

namespace streetsim {

std::vector<VulkanDeviceInfo> ListVulkanDevices() {
  auto instance = vulkan::Instance::Create(/*enable_validation=*/false);
  if (!instance.ok()) return {};
  auto devices = (*instance)->PhysicalDevices();
  if (!devices.ok()) return {};
  std::vector<VulkanDeviceInfo> out;
  for (VkPhysicalDevice d : *devices) out.push_back(vulkan::DescribeDevice(d));
  return out;
}

bool HasVulkanGpu() {
  for (const auto& d : ListVulkanDevices()) {
    if (!d.is_cpu) return true;
  }
  return false;
}

}  // namespace streetsim
