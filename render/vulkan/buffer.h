// RAII VkBuffer + VkDeviceMemory (internal). One allocation per buffer: the engine has a few dozen
// long-lived buffers, far below maxMemoryAllocationCount, so no sub-allocator is needed.
#pragma once

#include <vulkan/vulkan.h>

#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/vulkan/context.h"

namespace streetsim::vulkan {

class Buffer {
 public:
  enum class Kind {
    kDevice,    // device-local working buffer (storage, transfer, indirect)
    kStaging,   // host-visible, coherent, mapped: host -> device uploads
    kReadback,  // host-visible, mapped, preferably cached: device -> host
  };

  Buffer() = default;
  // `size_bytes` is rounded up to at least 16 (zero-sized buffers are not allowed).
  static absl::StatusOr<Buffer> Create(const Context& ctx, VkDeviceSize size_bytes, Kind kind,
                                       std::string name);
  ~Buffer() { Reset(); }
  Buffer(Buffer&& other) noexcept { *this = std::move(other); }
  Buffer& operator=(Buffer&& other) noexcept;
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;

  // Reallocates when smaller than `size_bytes` (contents are not preserved); grows by at least
  // 1.5x so that slowly rising demand does not reallocate every frame.
  absl::Status EnsureSize(const Context& ctx, VkDeviceSize size_bytes);

  VkBuffer handle() const { return buffer_; }
  VkDeviceSize size() const { return size_; }
  bool valid() const { return buffer_ != VK_NULL_HANDLE; }
  const std::string& name() const { return name_; }
  // Host pointer for kStaging / kReadback; nullptr for kDevice.
  void* mapped() const { return mapped_; }
  // Makes device writes visible to the host (no-op on coherent memory).
  absl::Status InvalidateForHost() const;

 private:
  void Reset();

  VkDevice device_ = VK_NULL_HANDLE;
  VkBuffer buffer_ = VK_NULL_HANDLE;
  VkDeviceMemory memory_ = VK_NULL_HANDLE;
  VkDeviceSize size_ = 0;
  Kind kind_ = Kind::kDevice;
  bool coherent_ = true;
  void* mapped_ = nullptr;
  std::string name_;
};

// Creates `*buffer` on first use, else grows it to at least `bytes` (contents not kept).
absl::Status EnsureBufferCapacity(const Context& ctx, Buffer* buffer, VkDeviceSize bytes, Buffer::Kind kind,
                                  const char* name);

// Host -> device copy through a staging buffer of bounded size: `fill(begin, end, out)` writes
// source bytes [begin, end) to `out`; chunk boundaries are multiples of `granularity`.
absl::Status UploadWith(const Context& ctx, const Buffer& dst, size_t bytes, size_t granularity,
                        const std::function<void(size_t begin, size_t end, std::byte* out)>& fill);
absl::Status UploadBytes(const Context& ctx, const Buffer& dst, const void* data, size_t bytes);
// Device -> host copy of the first `bytes` of `src` (tests and debugging; frames use their own
// readback buffer).
absl::Status DownloadBytes(const Context& ctx, const Buffer& src, void* data, size_t bytes);

}  // namespace streetsim::vulkan
