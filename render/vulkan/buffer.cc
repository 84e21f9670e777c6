#include "render/vulkan/buffer.h"

#include <algorithm>
#include <cstring>
#include <utility>

#include "absl/strings/str_cat.h"

namespace streetsim::vulkan {

absl::StatusOr<Buffer> Buffer::Create(const Context& ctx, VkDeviceSize size_bytes, Kind kind,
                                      std::string name) {
  Buffer b;
  b.device_ = ctx.device();
  b.kind_ = kind;
  b.name_ = std::move(name);
  b.size_ = std::max<VkDeviceSize>(16, (size_bytes + 15) / 16 * 16);
  if (kind == Kind::kDevice && b.size_ > ctx.limits().maxStorageBufferRange) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "vulkan: buffer '", b.name_, "' needs ", b.size_,
        " bytes, more than maxStorageBufferRange ", ctx.limits().maxStorageBufferRange));
  }

  VkBufferCreateInfo info{VK_STRUCTURE_TYPE_BUFFER_CREATE_INFO};
  info.size = b.size_;
  info.usage = kind == Kind::kDevice
                   ? VK_BUFFER_USAGE_STORAGE_BUFFER_BIT | VK_BUFFER_USAGE_TRANSFER_SRC_BIT |
                         VK_BUFFER_USAGE_TRANSFER_DST_BIT | VK_BUFFER_USAGE_INDIRECT_BUFFER_BIT
                   : VK_BUFFER_USAGE_TRANSFER_SRC_BIT | VK_BUFFER_USAGE_TRANSFER_DST_BIT;
  info.sharingMode = VK_SHARING_MODE_EXCLUSIVE;
  STREETSIM_VK_RETURN_IF_ERROR(vkCreateBuffer(b.device_, &info, nullptr, &b.buffer_),
                               absl::StrCat("vkCreateBuffer(", b.name_, ")"));

  VkMemoryRequirements req;
  vkGetBufferMemoryRequirements(b.device_, b.buffer_, &req);
  VkMemoryPropertyFlags required = 0, preferred = 0;
  switch (kind) {
    case Kind::kDevice:
      required = VK_MEMORY_PROPERTY_DEVICE_LOCAL_BIT;
      break;
    case Kind::kStaging:
      required = VK_MEMORY_PROPERTY_HOST_VISIBLE_BIT | VK_MEMORY_PROPERTY_HOST_COHERENT_BIT;
      break;
    case Kind::kReadback:
      required = VK_MEMORY_PROPERTY_HOST_VISIBLE_BIT;
      preferred = VK_MEMORY_PROPERTY_HOST_CACHED_BIT;
      break;
  }
  auto type = ctx.FindMemoryType(req.memoryTypeBits, required, preferred);
  if (!type.ok() && kind == Kind::kDevice) {
    // Some devices expose no DEVICE_LOCAL type for storage buffers; any type works there.
    type = ctx.FindMemoryType(req.memoryTypeBits, 0, 0);
  }
  if (!type.ok()) return type.status();

  VkMemoryAllocateInfo alloc{VK_STRUCTURE_TYPE_MEMORY_ALLOCATE_INFO};
  alloc.allocationSize = req.size;
  alloc.memoryTypeIndex = *type;
  STREETSIM_VK_RETURN_IF_ERROR(vkAllocateMemory(b.device_, &alloc, nullptr, &b.memory_),
                               absl::StrCat("vkAllocateMemory(", b.name_, ", ", req.size, " B)"));
  STREETSIM_VK_RETURN_IF_ERROR(vkBindBufferMemory(b.device_, b.buffer_, b.memory_, 0),
                               "vkBindBufferMemory");
  if (kind != Kind::kDevice) {
    STREETSIM_VK_RETURN_IF_ERROR(vkMapMemory(b.device_, b.memory_, 0, VK_WHOLE_SIZE, 0, &b.mapped_),
                                 "vkMapMemory");
    VkPhysicalDeviceMemoryProperties mem;
    vkGetPhysicalDeviceMemoryProperties(ctx.physical_device(), &mem);
    b.coherent_ =
        (mem.memoryTypes[*type].propertyFlags & VK_MEMORY_PROPERTY_HOST_COHERENT_BIT) != 0;
  }
  return b;
}

Buffer& Buffer::operator=(Buffer&& other) noexcept {
  if (this != &other) {
    Reset();
    device_ = std::exchange(other.device_, VK_NULL_HANDLE);
    buffer_ = std::exchange(other.buffer_, VK_NULL_HANDLE);
    memory_ = std::exchange(other.memory_, VK_NULL_HANDLE);
    size_ = std::exchange(other.size_, 0);
    kind_ = other.kind_;
    coherent_ = other.coherent_;
    mapped_ = std::exchange(other.mapped_, nullptr);
    name_ = std::move(other.name_);
  }
  return *this;
}

void Buffer::Reset() {
  if (device_ == VK_NULL_HANDLE) return;
  if (mapped_ != nullptr) vkUnmapMemory(device_, memory_);
  if (buffer_ != VK_NULL_HANDLE) vkDestroyBuffer(device_, buffer_, nullptr);
  if (memory_ != VK_NULL_HANDLE) vkFreeMemory(device_, memory_, nullptr);
  buffer_ = VK_NULL_HANDLE;
  memory_ = VK_NULL_HANDLE;
  mapped_ = nullptr;
  size_ = 0;
}

absl::Status Buffer::EnsureSize(const Context& ctx, VkDeviceSize size_bytes) {
  if (valid() && size_ >= size_bytes) return absl::OkStatus();
  const VkDeviceSize grown = valid() ? std::max(size_bytes, size_ + size_ / 2) : size_bytes;
  std::string name = name_;
  const Kind kind = kind_;
  Reset();  // free first so that peak memory is not old + new
  auto fresh = Create(ctx, grown, kind, name);
  if (!fresh.ok() && grown > size_bytes) fresh = Create(ctx, size_bytes, kind, name);
  if (!fresh.ok()) {
    name_ = std::move(name);
    return fresh.status();
  }
  *this = *std::move(fresh);
  return absl::OkStatus();
}

absl::Status Buffer::InvalidateForHost() const {
  if (coherent_ || mapped_ == nullptr) return absl::OkStatus();
  VkMappedMemoryRange range{VK_STRUCTURE_TYPE_MAPPED_MEMORY_RANGE};
  range.memory = memory_;
  range.offset = 0;
  range.size = VK_WHOLE_SIZE;
  STREETSIM_VK_RETURN_IF_ERROR(vkInvalidateMappedMemoryRanges(device_, 1, &range),
                               "vkInvalidateMappedMemoryRanges");
  return absl::OkStatus();
}

namespace {
constexpr size_t kStagingChunkBytes = size_t{48} << 20;
}  // namespace

absl::Status EnsureBufferCapacity(const Context& ctx, Buffer* buffer, VkDeviceSize bytes, Buffer::Kind kind,
                                  const char* name) {
  if (!buffer->valid()) {
    auto created = Buffer::Create(ctx, bytes, kind, name);
    if (!created.ok()) return created.status();
    *buffer = *std::move(created);
    return absl::OkStatus();
  }
  return buffer->EnsureSize(ctx, bytes);
}

absl::Status UploadWith(const Context& ctx, const Buffer& dst, size_t bytes, size_t granularity,
                        const std::function<void(size_t begin, size_t end, std::byte* out)>& fill) {
  if (bytes == 0) return absl::OkStatus();
  if (bytes > dst.size()) return absl::InternalError("vulkan: upload larger than its buffer");
  const size_t chunk = std::max(granularity, kStagingChunkBytes / granularity * granularity);
  auto staging = Buffer::Create(ctx, std::min(chunk, bytes), Buffer::Kind::kStaging, "staging");
  if (!staging.ok()) return staging.status();
  for (size_t begin = 0; begin < bytes; begin += chunk) {
    const size_t end = std::min(bytes, begin + chunk);
    fill(begin, end, static_cast<std::byte*>(staging->mapped()));
    const VkBufferCopy region{0, begin, end - begin};
    if (absl::Status s = ctx.SubmitAndWait([&](VkCommandBuffer cmd) {
          vkCmdCopyBuffer(cmd, staging->handle(), dst.handle(), 1, &region);
        });
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

absl::Status UploadBytes(const Context& ctx, const Buffer& dst, const void* data, size_t bytes) {
  return UploadWith(ctx, dst, bytes, 4, [data](size_t begin, size_t end, std::byte* out) {
    std::memcpy(out, static_cast<const std::byte*>(data) + begin, end - begin);
  });
}

absl::Status DownloadBytes(const Context& ctx, const Buffer& src, void* data, size_t bytes) {
  if (bytes == 0) return absl::OkStatus();
  auto readback = Buffer::Create(ctx, bytes, Buffer::Kind::kReadback, "download");
  if (!readback.ok()) return readback.status();
  const VkBufferCopy region{0, 0, bytes};
  if (absl::Status s = ctx.SubmitAndWait([&](VkCommandBuffer cmd) {
        vkCmdCopyBuffer(cmd, src.handle(), readback->handle(), 1, &region);
        VkMemoryBarrier to_host{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
        to_host.srcAccessMask = VK_ACCESS_TRANSFER_WRITE_BIT;
        to_host.dstAccessMask = VK_ACCESS_HOST_READ_BIT;
        vkCmdPipelineBarrier(cmd, VK_PIPELINE_STAGE_TRANSFER_BIT, VK_PIPELINE_STAGE_HOST_BIT, 0, 1,
                             &to_host, 0, nullptr, 0, nullptr);
      });
      !s.ok()) {
    return s;
  }
  if (absl::Status s = readback->InvalidateForHost(); !s.ok()) return s;
  std::memcpy(data, readback->mapped(), bytes);
  return absl::OkStatus();
}

}  // namespace streetsim::vulkan
