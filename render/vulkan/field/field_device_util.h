// Small host-side steps shared by the Vulkan fields (VulkanField, VulkanExtendedField): a field's
// frame objects (command buffer, fence, timestamp pool, profiler, descriptor arena) with their
// per-batch steps, the download-and-add of a device gradient into a host array, and wall time.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>

#include <vulkan/vulkan.h>

#include "absl/status/status.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"

namespace streetsim::field {

// A field's reusable command buffer, recorded and submitted once per batch (vulkan::CreateFrameObjects
// with 2 timestamp queries, and a descriptor arena). Declare it after the field's Context, which
// must outlive it, and after the buffers its batches use: its destructor waits for the device
// before anything is freed.
struct FieldFrame {
  FieldFrame() = default;
  FieldFrame(const FieldFrame&) = delete;
  FieldFrame& operator=(const FieldFrame&) = delete;
  ~FieldFrame();

  absl::Status Create(const vulkan::Context& c);
  // Resets the command buffer and arena, begins recording, attaches the profiler (STREETSIM_VK_PROFILE=1:
  // per-kernel times in the log) and resets the timestamps. `rec` records on cmd and arena.
  absl::Status Begin(vulkan::Recorder& rec);
  // Timestamp `query` (0: start, 1: end) at the bottom of the pipe: written once what was recorded
  // before it has finished. Nothing without a timestamp pool.
  void WriteTimestamp(uint32_t query) const;
  // vulkan::SubmitFrameAndWait with this frame's fence and profiler.
  absl::Status SubmitAndWait(vulkan::Recorder& rec, vulkan::Buffer& readback) const;
  // Milliseconds between timestamps 0 and 1 of the last batch (0 without a pool or on failure).
  double ReadTimestampsMs() const;

  const vulkan::Context* ctx = nullptr;
  VkCommandBuffer cmd = VK_NULL_HANDLE;
  VkFence fence = VK_NULL_HANDLE;
  VkQueryPool query_pool = VK_NULL_HANDLE;
  std::unique_ptr<vulkan::Profiler> profiler;
  std::unique_ptr<vulkan::DescriptorArena> arena;
};

// dst[i] += the first `floats` floats of the device buffer `src`, through `readback` (a kReadback
// buffer, made or grown as needed): one submit, then a host add split over a few threads when
// large (memory-bound: the spec's plane gradient is 35.7 M floats).
absl::Status DownloadAdd(const vulkan::Context& ctx, const vulkan::Buffer& src, size_t floats,
                         vulkan::Buffer* readback, float* dst);

inline double MsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace streetsim::field
