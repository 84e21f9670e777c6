// Small host-side steps shared by the Vulkan fields (VulkanField, VulkanExtendedField): the
// per-batch device time from a 2-query timestamp pool, the download-and-add of a device gradient
// into a host array, and the release of a field's frame objects.
#pragma once

#include <cstddef>

#include <vulkan/vulkan.h>

#include "absl/status/status.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"

namespace streetsim::field {

// Milliseconds between timestamps 0 and 1 of `pool` (0 without a pool or on failure).
double ReadBatchTimestampsMs(const vulkan::Context& ctx, VkQueryPool pool);

// dst[i] += the first `floats` floats of the device buffer `src`, through `readback` (a kReadback
// buffer, made or grown as needed): one submit, then a host add split over a few threads when
// large (memory-bound: the spec's plane gradient is 35.7 M floats).
absl::Status DownloadAdd(const vulkan::Context& ctx, const vulkan::Buffer& src, size_t floats,
                         vulkan::Buffer* readback, float* dst);

// Waits for the device, then destroys what vulkan::CreateFrameObjects made (null handles skipped).
void DestroyFrameObjects(const vulkan::Context& ctx, VkCommandBuffer cmd, VkFence fence, VkQueryPool pool);

}  // namespace streetsim::field
