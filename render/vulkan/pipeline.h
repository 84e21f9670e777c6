// Compute pipelines from embedded SPIR-V, and the recorder that binds buffers and records
// dispatches into a frame's command buffer (internal).
#pragma once

#include <vulkan/vulkan.h>

#include <cstdint>
#include <initializer_list>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"

namespace streetsim::vulkan {

struct SpecConstant {
  uint32_t id;
  uint32_t value;
};

// One compute shader: its descriptor set layout (bindings 0..num_buffers-1, all storage buffers),
// push constant range and pipeline.
class ComputePipeline {
 public:
  static absl::StatusOr<std::unique_ptr<ComputePipeline>> Create(
      const Context& ctx, std::string name, std::span<const uint32_t> spirv, int num_buffers,
      uint32_t push_constant_bytes, std::span<const SpecConstant> spec_constants = {});
  ~ComputePipeline();
  ComputePipeline(const ComputePipeline&) = delete;
  ComputePipeline& operator=(const ComputePipeline&) = delete;

  const std::string& name() const { return name_; }
  VkPipeline pipeline() const { return pipeline_; }
  VkPipelineLayout layout() const { return layout_; }
  VkDescriptorSetLayout set_layout() const { return set_layout_; }
  int num_buffers() const { return num_buffers_; }
  uint32_t push_constant_bytes() const { return push_constant_bytes_; }

 private:
  ComputePipeline() = default;
  VkDevice device_ = VK_NULL_HANDLE;
  std::string name_;
  VkDescriptorSetLayout set_layout_ = VK_NULL_HANDLE;
  VkPipelineLayout layout_ = VK_NULL_HANDLE;
  VkPipeline pipeline_ = VK_NULL_HANDLE;
  int num_buffers_ = 0;
  uint32_t push_constant_bytes_ = 0;
};

// One row of a kernel table: creates the pipeline into *out (Kernels::Create, LidarKernels::Create).
struct PipelineSpec {
  std::unique_ptr<ComputePipeline>* out;
  const char* name;
  std::span<const uint32_t> spirv;
  int buffers;
  uint32_t push_bytes;
  std::span<const SpecConstant> spec;
};
absl::Status CreatePipelines(const Context& ctx, std::span<const PipelineSpec> specs);

// Descriptor sets for one frame: allocated per dispatch and released together by Reset() once
// the frame's fence has signalled. Buffers are reallocated on growth, so sets are never cached.
class DescriptorArena {
 public:
  explicit DescriptorArena(VkDevice device) : device_(device) {}
  ~DescriptorArena();
  DescriptorArena(const DescriptorArena&) = delete;
  DescriptorArena& operator=(const DescriptorArena&) = delete;

  absl::StatusOr<VkDescriptorSet> Allocate(VkDescriptorSetLayout layout);
  absl::Status Reset();

 private:
  absl::Status AddPool();
  VkDevice device_;
  std::vector<VkDescriptorPool> pools_;
  size_t current_ = 0;
};

// Dispatch grid for `groups` workgroups: 1D when it fits maxComputeWorkGroupCount[0], else 2D;
// kernels linearise (common.glsl: linear_group_id) and early-out past their count.
struct Grid {
  uint32_t x = 0, y = 1;
};
Grid GridFor(uint64_t groups);
inline constexpr uint32_t kMaxGridX = 16384;  // common.glsl: MAX_GRID_X

// Per-dispatch device timing for tuning (STREETSIM_VK_PROFILE=1): a timestamp after every
// barrier, labelled with the kernels recorded since the previous one.
class Profiler {
 public:
  static constexpr uint32_t kMaxQueries = 1024;
  static absl::StatusOr<std::unique_ptr<Profiler>> Create(const Context& ctx);
  ~Profiler();
  void Begin(VkCommandBuffer cmd);
  void Mark(VkCommandBuffer cmd, const std::string& label);
  // Logs milliseconds per label (summed over repeats) at INFO.
  void Report(const Context& ctx) const;

 private:
  Profiler() = default;
  VkDevice device_ = VK_NULL_HANDLE;
  VkQueryPool pool_ = VK_NULL_HANDLE;
  std::vector<std::string> labels_;
};

// Records a sequence of compute dispatches. The first error sticks (status()), later calls are
// no-ops, so stage code reads straight through and the frame checks once.
class Recorder {
 public:
  Recorder(const Context& ctx, VkCommandBuffer cmd, DescriptorArena* arena)
      : ctx_(ctx), cmd_(cmd), arena_(arena) {}

  VkCommandBuffer cmd() const { return cmd_; }
  const Context& ctx() const { return ctx_; }
  void set_profiler(Profiler* profiler) { profiler_ = profiler; }
  const absl::Status& status() const { return status_; }
  void Fail(absl::Status s) {
    if (status_.ok()) status_ = std::move(s);
  }

  template <typename Push>
  void Dispatch(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                const Push& push, Grid grid) {
    DispatchImpl(p, buffers, &push, sizeof(Push), grid, nullptr, 0);
  }
  void Dispatch(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers, Grid grid) {
    DispatchImpl(p, buffers, nullptr, 0, grid, nullptr, 0);
  }
  // Grid read from `args` at `args_offset` (a VkDispatchIndirectCommand written on the device).
  template <typename Push>
  void DispatchIndirect(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                        const Push& push, const Buffer& args, VkDeviceSize args_offset) {
    DispatchImpl(p, buffers, &push, sizeof(Push), Grid{}, &args, args_offset);
  }

  void DispatchIndirect(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                        const Buffer& args, VkDeviceSize args_offset) {
    DispatchImpl(p, buffers, nullptr, 0, Grid{}, &args, args_offset);
  }

  // Orders every earlier compute/transfer write before every later compute/indirect/transfer
  // access. Stages are a chain, so one global barrier between them is all that is needed.
  void Barrier();
  // Makes transfer writes (readback copies) visible to the host after the fence.
  void HostReadBarrier();
  void Fill(const Buffer& buffer, VkDeviceSize offset, VkDeviceSize size, uint32_t value);
  void Update(const Buffer& buffer, VkDeviceSize offset, std::span<const uint32_t> words);
  void Copy(const Buffer& src, VkDeviceSize src_offset, const Buffer& dst, VkDeviceSize dst_offset,
            VkDeviceSize size);

 private:
  void DispatchImpl(const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                    const void* push, size_t push_size, Grid grid, const Buffer* args,
                    VkDeviceSize args_offset);
  const Context& ctx_;
  VkCommandBuffer cmd_;
  DescriptorArena* arena_;
  absl::Status status_;
  Profiler* profiler_ = nullptr;
  std::string pending_label_;
};

// A renderer's reusable command buffer, recorded and submitted once per frame (the camera engine
// and the LiDAR renderer share these steps). CreateFrameObjects allocates the command buffer and
// its fence, a pool of `num_timestamps` timestamp queries where the device has timestamps (else
// left null) and, with STREETSIM_VK_PROFILE=1, a profiler (left null when it cannot be made); on
// an error, what was made is already in the outputs for the caller to destroy.
// BeginFrameCommands resets `cmd` and the descriptor arena and begins one-time recording;
// AttachProfiler (null: none) starts its timestamps.
absl::Status CreateFrameObjects(const Context& ctx, uint32_t num_timestamps, VkCommandBuffer* cmd,
                                VkFence* fence, VkQueryPool* query_pool, std::unique_ptr<Profiler>* profiler);
absl::Status BeginFrameCommands(VkCommandBuffer cmd, DescriptorArena& arena);
void AttachProfiler(Recorder& rec, Profiler* profiler);
// Ends `rec`'s command buffer (or returns its sticky error), submits it, waits on `fence` and
// makes `readback` visible to the host; then reports the profiler's times, if any.
absl::Status SubmitFrameAndWait(const Context& ctx, Recorder& rec, VkFence fence, Buffer& readback,
                                const Profiler* profiler);

}  // namespace streetsim::vulkan
