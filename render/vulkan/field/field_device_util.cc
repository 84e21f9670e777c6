#include "render/vulkan/field/field_device_util.h"

#include <algorithm>
#include <thread>
#include <vector>

namespace streetsim::field {

namespace vk = vulkan;

namespace {

void AddInto(float* dst, const float* src, size_t n) {
  constexpr size_t kPerThread = size_t{1} << 22;
  const size_t threads = std::min<size_t>({8, std::max(1u, std::thread::hardware_concurrency()), n / kPerThread + 1});
  auto add = [&](size_t b, size_t e) {
    for (size_t i = b; i < e; ++i) dst[i] += src[i];
  };
  if (threads <= 1) return add(0, n);
  std::vector<std::thread> pool;
  const size_t step = (n + threads - 1) / threads;
  for (size_t t = 1; t < threads; ++t) pool.emplace_back(add, std::min(n, t * step), std::min(n, (t + 1) * step));
  add(0, std::min(n, step));
  for (std::thread& t : pool) t.join();
}

}  // namespace

FieldFrame::~FieldFrame() {
  if (ctx == nullptr) return;
  VkDevice dev = ctx->device();
  vkDeviceWaitIdle(dev);
  if (query_pool != VK_NULL_HANDLE) vkDestroyQueryPool(dev, query_pool, nullptr);
  if (fence != VK_NULL_HANDLE) vkDestroyFence(dev, fence, nullptr);
  if (cmd != VK_NULL_HANDLE) vkFreeCommandBuffers(dev, ctx->command_pool(), 1, &cmd);
}

absl::Status FieldFrame::Create(const vk::Context& c) {
  ctx = &c;  // first: on an error, what was made is destroyed with the frame
  arena = std::make_unique<vk::DescriptorArena>(c.device());
  return vk::CreateFrameObjects(c, 2, &cmd, &fence, &query_pool, &profiler);
}

absl::Status FieldFrame::Begin(vk::Recorder& rec) {
  if (auto s = vk::BeginFrameCommands(cmd, *arena); !s.ok()) return s;
  vk::AttachProfiler(rec, profiler.get());
  if (query_pool != VK_NULL_HANDLE) vkCmdResetQueryPool(cmd, query_pool, 0, 2);
  return absl::OkStatus();
}

void FieldFrame::WriteTimestamp(uint32_t query) const {
  if (query_pool != VK_NULL_HANDLE) vkCmdWriteTimestamp(cmd, VK_PIPELINE_STAGE_BOTTOM_OF_PIPE_BIT, query_pool, query);
}

absl::Status FieldFrame::SubmitAndWait(vk::Recorder& rec, vk::Buffer& readback) const {
  return vk::SubmitFrameAndWait(*ctx, rec, fence, readback, profiler.get());
}

double FieldFrame::ReadTimestampsMs() const {
  if (query_pool == VK_NULL_HANDLE) return 0;
  uint64_t ticks[2] = {0, 0};
  if (vkGetQueryPoolResults(ctx->device(), query_pool, 0, 2, sizeof(ticks), ticks, 8,
                            VK_QUERY_RESULT_64_BIT | VK_QUERY_RESULT_WAIT_BIT) != VK_SUCCESS) {
    return 0;
  }
  const uint32_t bits = ctx->timestamp_valid_bits();
  const uint64_t mask = bits >= 64 ? ~uint64_t{0} : ((uint64_t{1} << bits) - 1);
  return static_cast<double>((ticks[1] - ticks[0]) & mask) * ctx->timestamp_period_ns() * 1e-6;
}

absl::Status DownloadAdd(const vk::Context& ctx, const vk::Buffer& src, size_t floats, vk::Buffer* readback,
                         float* dst) {
  if (floats == 0) return absl::OkStatus();
  if (auto s = vk::EnsureBufferCapacity(ctx, readback, floats * sizeof(float), vk::Buffer::Kind::kReadback,
                                        "field grad readback");
      !s.ok()) {
    return s;
  }
  if (auto s = ctx.SubmitAndWait([&](VkCommandBuffer cmd) {
        const VkBufferCopy region{0, 0, floats * sizeof(float)};
        vkCmdCopyBuffer(cmd, src.handle(), readback->handle(), 1, &region);
        VkMemoryBarrier to_host{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
        to_host.srcAccessMask = VK_ACCESS_TRANSFER_WRITE_BIT;
        to_host.dstAccessMask = VK_ACCESS_HOST_READ_BIT;
        vkCmdPipelineBarrier(cmd, VK_PIPELINE_STAGE_TRANSFER_BIT, VK_PIPELINE_STAGE_HOST_BIT, 0, 1, &to_host, 0,
                             nullptr, 0, nullptr);
      });
      !s.ok()) {
    return s;
  }
  if (auto s = readback->InvalidateForHost(); !s.ok()) return s;
  AddInto(dst, static_cast<const float*>(readback->mapped()), floats);
  return absl::OkStatus();
}

}  // namespace streetsim::field
