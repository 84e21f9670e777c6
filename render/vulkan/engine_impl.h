// The vulkan Engine and DeviceScene classes (internal: the public API is vulkan_engine.h; tests
// reach in through testing.h).
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

inline constexpr size_t kMaxGaussians = size_t{1} << 26;

// A scene in device memory: the parameters (uploaded once) and the per-Gaussian working buffers
// of a frame, sized at Upload. Holds the Context so that its buffers never outlive the device.
class VulkanScene : public DeviceScene {
 public:
  VulkanScene(std::shared_ptr<const Context> ctx, uint64_t engine_id, uint32_t n, int sh_degree)
      : ctx_(std::move(ctx)), engine_id_(engine_id), n_(n), sh_degree_(sh_degree) {}
  size_t size() const override { return n_; }
  int sh_degree() const override { return sh_degree_; }
  uint64_t engine_id() const { return engine_id_; }
  SceneBuffers view() const;

  Buffer gauss, splats, sorted_splats, rects, flags, touched, touched_sorted;
  std::array<Buffer, kMaxShGroups> sh;  // groups past the degree's stay empty
  std::array<Buffer, 2> depth_keys, ids;

 private:
  std::shared_ptr<const Context> ctx_;
  uint64_t engine_id_;
  uint32_t n_;
  int sh_degree_;
};

class VulkanEngine : public Engine {
 public:
  static absl::StatusOr<std::unique_ptr<VulkanEngine>> Create(VulkanDevicePreference preference);
  ~VulkanEngine() override;

  Backend backend() const override { return Backend::kVulkan; }
  std::string device_name() const override { return ctx_->description(); }
  absl::StatusOr<std::unique_ptr<DeviceScene>> Upload(const GaussianStore& store) override;
  absl::Status Render(const DeviceScene& scene, const PinholeCamera& camera,
                      const RenderOptions& options, RenderOutput* out) override;
  absl::Status RenderBackward(const DeviceScene& scene, const RenderOutputGrads& grads,
                              const BackwardOptions& options, GaussianGrads* out) override;
  absl::Status UpdateScene(const GaussianStore& store,
                           std::unique_ptr<DeviceScene>* scene) override;
  // param_upload.cc: packed in parallel into one persistent staging buffer, one submission.
  absl::Status UpdateSceneParams(const GaussianParamsView& params,
                                 std::unique_ptr<DeviceScene>* scene) override;

  // Kernels outside the engine that write a scene's parameters in place (the serving form's,
  // render/vulkan/field/vulkan_serving_form.h): `record` records dispatches that write `scene`'s
  // geometry and SH buffers; they are submitted once, under the engine's lock, and the next
  // render sees them. What a backward pass kept of the scene is dropped. InvalidArgument for a
  // scene of another engine.
  absl::Status WriteSceneOnDevice(DeviceScene* scene,
                                  const std::function<void(Recorder&, const VulkanScene&)>& record);
  // The device, for those kernels' pipelines and buffers (they hold it as scenes do).
  std::shared_ptr<const Context> shared_context() const { return ctx_; }

  // For testing.cc.
  const Context& context() const { return *ctx_; }
  const Kernels& kernels() const { return *kernels_; }
  int rerenders() const { return rerenders_; }
  uint64_t instance_capacity() const { return instance_capacity_; }
  const Buffer& final_t() const { return final_t_; }
  const Buffer& n_contrib() const { return n_contrib_; }
  void set_force_pair_mode(bool force) { force_pair_mode_ = force; }
  // Caps the deterministic backward's slot buffer below the device's storage buffer range
  // (0: the device's), so that tests reach its ResourceExhausted path with small frames.
  void set_det_slot_limit_bytes(uint64_t bytes) { det_slot_limit_bytes_ = bytes; }

 private:
  VulkanEngine() = default;
  uint32_t rank_bits(uint32_t n, uint32_t width, uint32_t height) const {
    return force_pair_mode_ ? 0 : RankBits(n, DivUp(width, kTileSize) * DivUp(height, kTileSize));
  }
  absl::Status EnsureFrameResources(uint32_t n, uint32_t width, uint32_t height, uint64_t capacity);
  // Records, submits and waits for one frame; fills `counts` (kNumCounts) from the readback.
  absl::Status RenderOnce(const VulkanScene& scene, const PinholeCamera& camera,
                          const RenderOptions& options, uint32_t* counts);
  absl::Status Readback(const PinholeCamera& camera, const RenderOptions& options,
                        RenderOutput* out);
  // Copies the store's parameters into the scene's buffers (sizes already match).
  absl::Status UploadParams(const GaussianStore& store, VulkanScene* scene);
  absl::Status EnsureBackwardResources(const VulkanScene& scene, uint32_t pixels);
  // Ends the recording of cmd_ (after a host-read barrier), submits it, waits for the fence and
  // makes `readback` visible to the host: the one submission of a forward or backward pass.
  absl::Status SubmitAndWait(Recorder& rec, Buffer& readback);

  std::shared_ptr<Context> ctx_;
  std::unique_ptr<Kernels> kernels_;
  std::unique_ptr<DescriptorArena> arena_;
  uint64_t id_ = 0;
  VkCommandBuffer cmd_ = VK_NULL_HANDLE;
  VkFence fence_ = VK_NULL_HANDLE;
  VkQueryPool query_pool_ = VK_NULL_HANDLE;

  ScanScratch scratch_;
  Buffer counts_, args_, hist_, ranges_;
  std::array<Buffer, 2> inst_keys_, inst_vals_;
  Buffer rgb_, depth_, alpha_, final_t_, n_contrib_;
  Buffer readback_;
  uint64_t instance_capacity_ = 0;
  uint64_t last_instances_ = 0;
  int rerenders_ = 0;
  bool force_pair_mode_ = false;
  // What RenderBackward needs from the last Render with keep_for_backward (its buffers stay
  // untouched until the next Render).
  struct Kept {
    const VulkanScene* scene = nullptr;
    ProjectPush push{};
    BlendParams blend{};
    BinningResult bins{};
    uint64_t instances = 0;  // I of the kept frame (sizes the deterministic backward's slots)
  } kept_;
  Buffer pixel_grads_, pixel_grads_staging_, splat_grads_, param_grads_, bwd_readback_;
  std::array<Buffer, kMaxShGroups> sh_grads_;
  Buffer det_slots_;  // deterministic backward: kDetSlotFloats per tile instance
  uint64_t det_slot_limit_bytes_ = 0;
  Buffer param_staging_;                 // UpdateSceneParams
  std::unique_ptr<ThreadPool> host_pool_;  // host-side packing / unpacking (created on first use)
  std::unique_ptr<Profiler> profiler_;  // STREETSIM_VK_PROFILE=1
  std::mutex mu_;                       // Render/Upload share the frame resources
};

}  // namespace streetsim::vulkan
