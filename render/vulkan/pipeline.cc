#include "render/vulkan/pipeline.h"

#include <algorithm>
#include <cstdlib>
#include <map>
#include <string_view>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"

namespace streetsim::vulkan {

absl::StatusOr<std::unique_ptr<ComputePipeline>> ComputePipeline::Create(
    const Context& ctx, std::string name, std::span<const uint32_t> spirv, int num_buffers,
    uint32_t push_constant_bytes, std::span<const SpecConstant> spec_constants) {
  auto p = std::unique_ptr<ComputePipeline>(new ComputePipeline());
  p->device_ = ctx.device();
  p->name_ = std::move(name);
  p->num_buffers_ = num_buffers;
  p->push_constant_bytes_ = push_constant_bytes;
  if (push_constant_bytes > ctx.limits().maxPushConstantsSize) {
    return absl::FailedPreconditionError(
        absl::StrCat("vulkan: ", p->name_, " needs ", push_constant_bytes,
                     " B of push constants, device has ", ctx.limits().maxPushConstantsSize));
  }

  std::vector<VkDescriptorSetLayoutBinding> bindings(num_buffers);
  for (int i = 0; i < num_buffers; ++i) {
    bindings[i] =
        VkDescriptorSetLayoutBinding{static_cast<uint32_t>(i), VK_DESCRIPTOR_TYPE_STORAGE_BUFFER, 1,
                                     VK_SHADER_STAGE_COMPUTE_BIT, nullptr};
  }
  VkDescriptorSetLayoutCreateInfo set_info{VK_STRUCTURE_TYPE_DESCRIPTOR_SET_LAYOUT_CREATE_INFO};
  set_info.bindingCount = static_cast<uint32_t>(bindings.size());
  set_info.pBindings = bindings.data();
  STREETSIM_VK_RETURN_IF_ERROR(
      vkCreateDescriptorSetLayout(p->device_, &set_info, nullptr, &p->set_layout_),
      "vkCreateDescriptorSetLayout");

  VkPushConstantRange range{VK_SHADER_STAGE_COMPUTE_BIT, 0, push_constant_bytes};
  VkPipelineLayoutCreateInfo layout_info{VK_STRUCTURE_TYPE_PIPELINE_LAYOUT_CREATE_INFO};
  layout_info.setLayoutCount = 1;
  layout_info.pSetLayouts = &p->set_layout_;
  layout_info.pushConstantRangeCount = push_constant_bytes > 0 ? 1 : 0;
  layout_info.pPushConstantRanges = &range;
  STREETSIM_VK_RETURN_IF_ERROR(
      vkCreatePipelineLayout(p->device_, &layout_info, nullptr, &p->layout_),
      "vkCreatePipelineLayout");

  VkShaderModuleCreateInfo module_info{VK_STRUCTURE_TYPE_SHADER_MODULE_CREATE_INFO};
  module_info.codeSize = spirv.size_bytes();
  module_info.pCode = spirv.data();
  VkShaderModule module = VK_NULL_HANDLE;
  STREETSIM_VK_RETURN_IF_ERROR(vkCreateShaderModule(p->device_, &module_info, nullptr, &module),
                               absl::StrCat("vkCreateShaderModule(", p->name_, ")"));

  std::vector<VkSpecializationMapEntry> entries;
  std::vector<uint32_t> values;
  for (const SpecConstant& c : spec_constants) {
    entries.push_back(
        {c.id, static_cast<uint32_t>(values.size() * sizeof(uint32_t)), sizeof(uint32_t)});
    values.push_back(c.value);
  }
  VkSpecializationInfo spec{static_cast<uint32_t>(entries.size()), entries.data(),
                            values.size() * sizeof(uint32_t), values.data()};
  VkComputePipelineCreateInfo info{VK_STRUCTURE_TYPE_COMPUTE_PIPELINE_CREATE_INFO};
  info.stage = VkPipelineShaderStageCreateInfo{VK_STRUCTURE_TYPE_PIPELINE_SHADER_STAGE_CREATE_INFO};
  info.stage.stage = VK_SHADER_STAGE_COMPUTE_BIT;
  info.stage.module = module;
  info.stage.pName = "main";
  info.stage.pSpecializationInfo = entries.empty() ? nullptr : &spec;
  info.layout = p->layout_;
  const VkResult r =
      vkCreateComputePipelines(p->device_, VK_NULL_HANDLE, 1, &info, nullptr, &p->pipeline_);
  vkDestroyShaderModule(p->device_, module, nullptr);
  STREETSIM_VK_RETURN_IF_ERROR(r, absl::StrCat("vkCreateComputePipelines(", p->name_, ")"));
  return p;
}

ComputePipeline::~ComputePipeline() {
  if (pipeline_ != VK_NULL_HANDLE) vkDestroyPipeline(device_, pipeline_, nullptr);
  if (layout_ != VK_NULL_HANDLE) vkDestroyPipelineLayout(device_, layout_, nullptr);
  if (set_layout_ != VK_NULL_HANDLE) vkDestroyDescriptorSetLayout(device_, set_layout_, nullptr);
}

// ---------------------------------------------------------------------------------------------

namespace {
constexpr uint32_t kSetsPerPool = 256;
constexpr uint32_t kBuffersPerPool = kSetsPerPool * 8;
}  // namespace

DescriptorArena::~DescriptorArena() {
  for (VkDescriptorPool pool : pools_) vkDestroyDescriptorPool(device_, pool, nullptr);
}

absl::Status DescriptorArena::AddPool() {
  VkDescriptorPoolSize size{VK_DESCRIPTOR_TYPE_STORAGE_BUFFER, kBuffersPerPool};
  VkDescriptorPoolCreateInfo info{VK_STRUCTURE_TYPE_DESCRIPTOR_POOL_CREATE_INFO};
  info.maxSets = kSetsPerPool;
  info.poolSizeCount = 1;
  info.pPoolSizes = &size;
  VkDescriptorPool pool = VK_NULL_HANDLE;
  STREETSIM_VK_RETURN_IF_ERROR(vkCreateDescriptorPool(device_, &info, nullptr, &pool),
                               "vkCreateDescriptorPool");
  pools_.push_back(pool);
  return absl::OkStatus();
}

absl::StatusOr<VkDescriptorSet> DescriptorArena::Allocate(VkDescriptorSetLayout layout) {
  for (;;) {
    if (current_ == pools_.size()) {
      if (absl::Status s = AddPool(); !s.ok()) return s;
    }
    VkDescriptorSetAllocateInfo info{VK_STRUCTURE_TYPE_DESCRIPTOR_SET_ALLOCATE_INFO};
    info.descriptorPool = pools_[current_];
    info.descriptorSetCount = 1;
    info.pSetLayouts = &layout;
    VkDescriptorSet set = VK_NULL_HANDLE;
    const VkResult r = vkAllocateDescriptorSets(device_, &info, &set);
    if (r == VK_SUCCESS) return set;
    if (r != VK_ERROR_OUT_OF_POOL_MEMORY && r != VK_ERROR_FRAGMENTED_POOL) {
      return VkStatus(r, "vkAllocateDescriptorSets");
    }
    ++current_;  // this pool is full: move on to the next (created on demand)
  }
}

absl::Status DescriptorArena::Reset() {
  for (VkDescriptorPool pool : pools_) {
    STREETSIM_VK_RETURN_IF_ERROR(vkResetDescriptorPool(device_, pool, 0), "vkResetDescriptorPool");
  }
  current_ = 0;
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------------------------

Grid GridFor(uint64_t groups) {
  if (groups <= kMaxGridX) return Grid{static_cast<uint32_t>(groups), 1};
  return Grid{kMaxGridX, static_cast<uint32_t>((groups + kMaxGridX - 1) / kMaxGridX)};
}

void Recorder::DispatchImpl(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                            const void* push, size_t push_size, Grid grid, const Buffer* args,
                            VkDeviceSize args_offset) {
  if (!status_.ok()) return;
  if (static_cast<int>(buffers.size()) != p.num_buffers() || push_size != p.push_constant_bytes()) {
    Fail(absl::InternalError(absl::StrCat("vulkan: ", p.name(), ": bound ", buffers.size(),
                                          " buffers / ", push_size, " B push constants, expects ",
                                          p.num_buffers(), " / ", p.push_constant_bytes())));
    return;
  }
  if (args == nullptr && (grid.x == 0 || grid.y == 0)) return;  // nothing to do
  if (profiler_ != nullptr) {
    absl::StrAppend(&pending_label_, pending_label_.empty() ? "" : "+", p.name());
  }
  auto set = arena_->Allocate(p.set_layout());
  if (!set.ok()) {
    Fail(set.status());
    return;
  }
  std::vector<VkDescriptorBufferInfo> infos;
  std::vector<VkWriteDescriptorSet> writes;
  infos.reserve(buffers.size());
  for (const Buffer* b : buffers) {
    infos.push_back(VkDescriptorBufferInfo{b->handle(), 0, VK_WHOLE_SIZE});
  }
  for (size_t i = 0; i < infos.size(); ++i) {
    VkWriteDescriptorSet w{VK_STRUCTURE_TYPE_WRITE_DESCRIPTOR_SET};
    w.dstSet = *set;
    w.dstBinding = static_cast<uint32_t>(i);
    w.descriptorCount = 1;
    w.descriptorType = VK_DESCRIPTOR_TYPE_STORAGE_BUFFER;
    w.pBufferInfo = &infos[i];
    writes.push_back(w);
  }
  vkUpdateDescriptorSets(ctx_.device(), static_cast<uint32_t>(writes.size()), writes.data(), 0,
                         nullptr);
  vkCmdBindPipeline(cmd_, VK_PIPELINE_BIND_POINT_COMPUTE, p.pipeline());
  vkCmdBindDescriptorSets(cmd_, VK_PIPELINE_BIND_POINT_COMPUTE, p.layout(), 0, 1, &*set, 0,
                          nullptr);
  if (push_size > 0) {
    vkCmdPushConstants(cmd_, p.layout(), VK_SHADER_STAGE_COMPUTE_BIT, 0,
                       static_cast<uint32_t>(push_size), push);
  }
  if (args != nullptr) {
    vkCmdDispatchIndirect(cmd_, args->handle(), args_offset);
  } else {
    vkCmdDispatch(cmd_, grid.x, grid.y, 1);
  }
}

void Recorder::Barrier() {
  if (!status_.ok()) return;
  VkMemoryBarrier barrier{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
  barrier.srcAccessMask = VK_ACCESS_SHADER_WRITE_BIT | VK_ACCESS_TRANSFER_WRITE_BIT;
  barrier.dstAccessMask = VK_ACCESS_SHADER_READ_BIT | VK_ACCESS_SHADER_WRITE_BIT |
                          VK_ACCESS_INDIRECT_COMMAND_READ_BIT | VK_ACCESS_TRANSFER_READ_BIT |
                          VK_ACCESS_TRANSFER_WRITE_BIT;
  vkCmdPipelineBarrier(cmd_, VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT | VK_PIPELINE_STAGE_TRANSFER_BIT,
                       VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT | VK_PIPELINE_STAGE_DRAW_INDIRECT_BIT |
                           VK_PIPELINE_STAGE_TRANSFER_BIT,
                       0, 1, &barrier, 0, nullptr, 0, nullptr);
  if (profiler_ != nullptr && !pending_label_.empty()) {
    profiler_->Mark(cmd_, pending_label_);
    pending_label_.clear();
  }
}

absl::StatusOr<std::unique_ptr<Profiler>> Profiler::Create(const Context& ctx) {
  auto p = std::unique_ptr<Profiler>(new Profiler());
  p->device_ = ctx.device();
  if (!ctx.has_timestamps()) return absl::FailedPreconditionError("no timestamps");
  VkQueryPoolCreateInfo info{VK_STRUCTURE_TYPE_QUERY_POOL_CREATE_INFO};
  info.queryType = VK_QUERY_TYPE_TIMESTAMP;
  info.queryCount = kMaxQueries;
  STREETSIM_VK_RETURN_IF_ERROR(vkCreateQueryPool(p->device_, &info, nullptr, &p->pool_),
                               "vkCreateQueryPool");
  return p;
}

Profiler::~Profiler() {
  if (pool_ != VK_NULL_HANDLE) vkDestroyQueryPool(device_, pool_, nullptr);
}

void Profiler::Begin(VkCommandBuffer cmd) {
  labels_.clear();
  vkCmdResetQueryPool(cmd, pool_, 0, kMaxQueries);
  Mark(cmd, "begin");
}

void Profiler::Mark(VkCommandBuffer cmd, const std::string& label) {
  if (labels_.size() >= kMaxQueries) return;
  vkCmdWriteTimestamp(cmd, VK_PIPELINE_STAGE_BOTTOM_OF_PIPE_BIT, pool_,
                      static_cast<uint32_t>(labels_.size()));
  labels_.push_back(label);
}

void Profiler::Report(const Context& ctx) const {
  if (labels_.size() < 2) return;
  std::vector<uint64_t> ticks(labels_.size());
  if (vkGetQueryPoolResults(device_, pool_, 0, static_cast<uint32_t>(labels_.size()),
                            ticks.size() * 8, ticks.data(), 8,
                            VK_QUERY_RESULT_64_BIT | VK_QUERY_RESULT_WAIT_BIT) != VK_SUCCESS) {
    return;
  }
  std::map<std::string, std::pair<double, int>> by_label;
  for (size_t i = 1; i < labels_.size(); ++i) {
    auto& entry = by_label[labels_[i]];
    entry.first += static_cast<double>(ticks[i] - ticks[i - 1]) * ctx.timestamp_period_ns() * 1e-6;
    ++entry.second;
  }
  for (const auto& [label, entry] : by_label) {
    LOG(INFO) << "vulkan profile: " << label << " x" << entry.second << ": " << entry.first
              << " ms";
  }
}

void Recorder::HostReadBarrier() {
  if (!status_.ok()) return;
  VkMemoryBarrier barrier{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
  barrier.srcAccessMask = VK_ACCESS_TRANSFER_WRITE_BIT;
  barrier.dstAccessMask = VK_ACCESS_HOST_READ_BIT;
  vkCmdPipelineBarrier(cmd_, VK_PIPELINE_STAGE_TRANSFER_BIT, VK_PIPELINE_STAGE_HOST_BIT, 0, 1,
                       &barrier, 0, nullptr, 0, nullptr);
}

void Recorder::Fill(const Buffer& buffer, VkDeviceSize offset, VkDeviceSize size, uint32_t value) {
  if (!status_.ok() || size == 0) return;
  vkCmdFillBuffer(cmd_, buffer.handle(), offset, size, value);
}

void Recorder::Update(const Buffer& buffer, VkDeviceSize offset, std::span<const uint32_t> words) {
  if (!status_.ok() || words.empty()) return;
  vkCmdUpdateBuffer(cmd_, buffer.handle(), offset, words.size_bytes(), words.data());
}

void Recorder::Copy(const Buffer& src, VkDeviceSize src_offset, const Buffer& dst,
                    VkDeviceSize dst_offset, VkDeviceSize size) {
  if (!status_.ok() || size == 0) return;
  VkBufferCopy region{src_offset, dst_offset, size};
  vkCmdCopyBuffer(cmd_, src.handle(), dst.handle(), 1, &region);
}

absl::Status CreatePipelines(const Context& ctx, std::span<const PipelineSpec> specs) {
  for (const PipelineSpec& s : specs) {
    auto p = ComputePipeline::Create(ctx, s.name, s.spirv, s.buffers, s.push_bytes, s.spec);
    if (!p.ok()) return p.status();
    *s.out = *std::move(p);
  }
  return absl::OkStatus();
}

absl::Status CreateFrameObjects(const Context& ctx, uint32_t num_timestamps, VkCommandBuffer* cmd,
                                VkFence* fence, VkQueryPool* query_pool, std::unique_ptr<Profiler>* profiler) {
  VkCommandBufferAllocateInfo alloc{VK_STRUCTURE_TYPE_COMMAND_BUFFER_ALLOCATE_INFO};
  alloc.commandPool = ctx.command_pool();
  alloc.level = VK_COMMAND_BUFFER_LEVEL_PRIMARY;
  alloc.commandBufferCount = 1;
  STREETSIM_VK_RETURN_IF_ERROR(vkAllocateCommandBuffers(ctx.device(), &alloc, cmd), "vkAllocateCommandBuffers");
  VkFenceCreateInfo fence_info{VK_STRUCTURE_TYPE_FENCE_CREATE_INFO};
  STREETSIM_VK_RETURN_IF_ERROR(vkCreateFence(ctx.device(), &fence_info, nullptr, fence), "vkCreateFence");
  if (ctx.has_timestamps()) {
    VkQueryPoolCreateInfo query_info{VK_STRUCTURE_TYPE_QUERY_POOL_CREATE_INFO};
    query_info.queryType = VK_QUERY_TYPE_TIMESTAMP;
    query_info.queryCount = num_timestamps;
    STREETSIM_VK_RETURN_IF_ERROR(vkCreateQueryPool(ctx.device(), &query_info, nullptr, query_pool),
                                 "vkCreateQueryPool");
  }
  if (const char* env = std::getenv("STREETSIM_VK_PROFILE"); env && std::string_view(env) == "1") {
    auto p = Profiler::Create(ctx);
    if (p.ok()) *profiler = *std::move(p);
  }
  return absl::OkStatus();
}

absl::Status BeginFrameCommands(VkCommandBuffer cmd, DescriptorArena& arena) {
  STREETSIM_VK_RETURN_IF_ERROR(vkResetCommandBuffer(cmd, 0), "vkResetCommandBuffer");
  if (absl::Status s = arena.Reset(); !s.ok()) return s;
  VkCommandBufferBeginInfo begin{VK_STRUCTURE_TYPE_COMMAND_BUFFER_BEGIN_INFO};
  begin.flags = VK_COMMAND_BUFFER_USAGE_ONE_TIME_SUBMIT_BIT;
  STREETSIM_VK_RETURN_IF_ERROR(vkBeginCommandBuffer(cmd, &begin), "vkBeginCommandBuffer");
  return absl::OkStatus();
}

void AttachProfiler(Recorder& rec, Profiler* profiler) {
  if (profiler) {
    profiler->Begin(rec.cmd());
    rec.set_profiler(profiler);
  }
}

absl::Status SubmitFrameAndWait(const Context& ctx, Recorder& rec, VkFence fence, Buffer& readback,
                                const Profiler* profiler) {
  VkCommandBuffer cmd = rec.cmd();
  rec.HostReadBarrier();
  if (!rec.status().ok()) {
    vkEndCommandBuffer(cmd);
    return rec.status();
  }
  STREETSIM_VK_RETURN_IF_ERROR(vkEndCommandBuffer(cmd), "vkEndCommandBuffer");
  STREETSIM_VK_RETURN_IF_ERROR(vkResetFences(ctx.device(), 1, &fence), "vkResetFences");
  VkSubmitInfo submit{VK_STRUCTURE_TYPE_SUBMIT_INFO};
  submit.commandBufferCount = 1;
  submit.pCommandBuffers = &cmd;
  STREETSIM_VK_RETURN_IF_ERROR(vkQueueSubmit(ctx.queue(), 1, &submit, fence), "vkQueueSubmit");
  STREETSIM_VK_RETURN_IF_ERROR(vkWaitForFences(ctx.device(), 1, &fence, VK_TRUE, UINT64_MAX),
                               "vkWaitForFences");
  if (absl::Status s = readback.InvalidateForHost(); !s.ok()) return s;
  if (profiler) profiler->Report(ctx);
  return absl::OkStatus();
}

}  // namespace streetsim::vulkan
