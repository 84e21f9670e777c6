// The vulkan engine: uploads scenes and records each frame into one command buffer (one submit,
// one fence wait). Stage recording lives in project.cc, binning.cc (with scan.cc and
// radix_sort.cc) and blend.cc.
#include "render/vulkan/vulkan_engine.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <string_view>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/engine_impl.h"
#include "streetsim_spirv.h"

namespace streetsim {
namespace vulkan {
namespace {

constexpr uint64_t kMinInstanceCapacity = 1 << 14;
constexpr uint32_t kNumTimestamps = 4;
constexpr VkDeviceSize kCountsBytes = kNumCounts * sizeof(uint32_t);

std::atomic<uint64_t> next_engine_id{1};

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
      .count();
}

}  // namespace

absl::StatusOr<std::unique_ptr<Kernels>> Kernels::Create(const Context& ctx) {
  auto k = std::make_unique<Kernels>();
  const SpecConstant saturate[] = {{0, 1}};
  const SpecConstant keys_only[] = {{0, 1}};
  const PipelineSpec specs[] = {
      {&k->project, "project", spirv::project, 9, sizeof(ProjectPush), {}},
      {&k->compact, "compact", spirv::compact, 6, 0, {}},
      {&k->setup_args, "setup_args", spirv::setup_args, 2, 8, {}},
      {&k->scan_block, "scan_block", spirv::scan_block, 3, 16, {}},
      {&k->scan_block_saturating, "scan_block_saturating", spirv::scan_block, 3, 16, saturate},
      {&k->scan_add, "scan_add", spirv::scan_add, 3, 16, {}},
      {&k->scan_add_saturating, "scan_add_saturating", spirv::scan_add, 3, 16, saturate},
      {&k->radix_hist, "radix_hist", spirv::radix_hist, 3, 8, {}},
      {&k->radix_scatter, "radix_scatter", spirv::radix_scatter, 6, 8, {}},
      {&k->radix_scatter_keys_only, "radix_scatter_keys_only", spirv::radix_scatter, 6, 8,
       keys_only},
      {&k->gather_sorted, "gather_sorted", spirv::gather_sorted, 6, 0, {}},
      {&k->emit, "emit", spirv::emit, 6, 12, {}},
      {&k->tile_ranges, "tile_ranges", spirv::tile_ranges, 3, 4, {}},
      {&k->blend, "blend", spirv::blend, 8, 28, {}},
  };
  if (absl::Status s = CreatePipelines(ctx, specs); !s.ok()) return s;
  for (uint32_t degree = 0; degree < k->project_backward.size(); ++degree) {
    const SpecConstant sh_degree[] = {{0, degree}};
    auto p = ComputePipeline::Create(ctx, "project_backward", spirv::project_backward, 13,
                                     sizeof(ProjectPush), sh_degree);
    if (!p.ok()) return p.status();
    k->project_backward[degree] = *std::move(p);
  }
  // The blend backward needs subgroup arithmetic (else RenderBackward is FailedPrecondition) and
  // uses float atomic adds when the device has them, a compare-and-swap loop otherwise.
  if (ctx.has_subgroup_arithmetic()) {
    const bool native = ctx.has_float_atomic_add();
    auto p = ComputePipeline::Create(ctx, native ? "blend_backward" : "blend_backward_cas",
                                     native ? spirv::blend_backward : spirv::blend_backward_cas, 7,
                                     28);
    if (!p.ok()) return p.status();
    k->blend_backward = *std::move(p);
  }
  return k;
}

SceneBuffers VulkanScene::view() const {
  return SceneBuffers{&gauss,
                      {&sh[0], sh[1].valid() ? &sh[1] : &sh[0], sh[2].valid() ? &sh[2] : &sh[0],
                       sh[3].valid() ? &sh[3] : &sh[0]},
                      &splats,
                      &sorted_splats,
                      &rects,
                      &flags,
                      &touched,
                      {&depth_keys[0], &depth_keys[1]},
                      {&ids[0], &ids[1]},
                      &touched_sorted};
}

absl::StatusOr<std::unique_ptr<VulkanEngine>> VulkanEngine::Create(
    VulkanDevicePreference preference) {
  auto engine = std::unique_ptr<VulkanEngine>(new VulkanEngine());
  auto ctx = Context::Create(preference);
  if (!ctx.ok()) return ctx.status();
  engine->ctx_ = std::shared_ptr<Context>(std::move(*ctx));
  const Context& c = *engine->ctx_;
  engine->id_ = next_engine_id.fetch_add(1);
  auto kernels = Kernels::Create(c);
  if (!kernels.ok()) return kernels.status();
  engine->kernels_ = *std::move(kernels);
  engine->arena_ = std::make_unique<DescriptorArena>(c.device());

  if (absl::Status s = CreateFrameObjects(c, kNumTimestamps, &engine->cmd_, &engine->fence_,
                                          &engine->query_pool_, &engine->profiler_);
      !s.ok()) {
    return s;
  }
  for (auto [buffer, bytes, name] :
       {std::tuple{&engine->counts_, kCountsBytes, "counts"},
        std::tuple{&engine->args_, VkDeviceSize{kNumArgs * kArgsSlotBytes}, "args"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, Buffer::Kind::kDevice, name); !s.ok()) {
      return s;
    }
  }
  return engine;
}

VulkanEngine::~VulkanEngine() {
  if (!ctx_) return;
  VkDevice device = ctx_->device();
  vkDeviceWaitIdle(device);
  if (query_pool_ != VK_NULL_HANDLE) vkDestroyQueryPool(device, query_pool_, nullptr);
  if (fence_ != VK_NULL_HANDLE) vkDestroyFence(device, fence_, nullptr);
  if (cmd_ != VK_NULL_HANDLE) vkFreeCommandBuffers(device, ctx_->command_pool(), 1, &cmd_);
}

absl::StatusOr<std::unique_ptr<DeviceScene>> VulkanEngine::Upload(const GaussianStore& store) {
  const size_t n = store.size();
  if (n > kMaxGaussians) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan: ", n, " Gaussians exceed the limit of ", kMaxGaussians, " (2^26)"));
  }
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  if (store.sh_degree < 0 || store.sh_degree > kMaxShDegree) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan: sh_degree ", store.sh_degree));
  }
  std::lock_guard<std::mutex> lock(mu_);
  const Context& c = *ctx_;
  auto scene = std::make_unique<VulkanScene>(ctx_, id_, static_cast<uint32_t>(n), store.sh_degree);
  const VkDeviceSize n64 = n;
  const int K = store.sh_coeffs();
  struct Alloc {
    Buffer* buffer;
    VkDeviceSize bytes;
    const char* name;
  };
  for (const Alloc& a :
       {Alloc{&scene->gauss, n64 * 48, "gauss"},
        Alloc{&scene->sh[0], n64 * ShGroupFloats(K, 0) * 4, "sh0"},
        Alloc{&scene->splats, n64 * 48, "splats"},
        Alloc{&scene->sorted_splats, n64 * 48, "sorted_splats"},
        Alloc{&scene->rects, n64 * 8, "rects"}, Alloc{&scene->flags, n64 * 4, "flags"},
        Alloc{&scene->touched, n64 * 4, "touched"},
        Alloc{&scene->touched_sorted, n64 * 4, "touched_sorted"},
        Alloc{&scene->depth_keys[0], n64 * 4, "depth_keys0"},
        Alloc{&scene->depth_keys[1], n64 * 4, "depth_keys1"},
        Alloc{&scene->ids[0], n64 * 4, "ids0"}, Alloc{&scene->ids[1], n64 * 4, "ids1"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, a.buffer, a.bytes, Buffer::Kind::kDevice, a.name);
        !s.ok()) {
      return s;
    }
  }
  if (absl::Status s = UploadParams(store, scene.get()); !s.ok()) return s;
  return std::unique_ptr<DeviceScene>(std::move(scene));
}

absl::Status VulkanEngine::UploadParams(const GaussianStore& store, VulkanScene* scene) {
  const Context& c = *ctx_;
  const size_t n = store.size();
  const VkDeviceSize n64 = n;
  const int K = store.sh_coeffs();
  absl::Status s = UploadGaussianGeometry(c, scene->gauss, store);
  if (!s.ok()) return s;
  for (int g = 0; g < kMaxShGroups && ShGroupFloats(K, g) > 0; ++g) {
    const size_t floats = ShGroupFloats(K, g);
    if (g > 0) {
      s = EnsureBufferCapacity(c, &scene->sh[g], n64 * floats * 4, Buffer::Kind::kDevice, "sh");
      if (!s.ok()) return s;
    }
    s = UploadWith(c, scene->sh[g], n * floats * 4, floats * 4,
                   [&](size_t begin, size_t end, std::byte* out) {
                     float* dst = reinterpret_cast<float*>(out);
                     for (size_t i = begin / (floats * 4); i < end / (floats * 4); ++i) {
                       std::memcpy(dst, &store.sh[(i * K + g * kShGroup) * 3], floats * 4);
                       dst += floats;
                     }
                   });
    if (!s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::Status VulkanEngine::EnsureFrameResources(uint32_t n, uint32_t width, uint32_t height,
                                                uint64_t capacity) {
  const Context& c = *ctx_;
  const uint64_t max_elements = c.limits().maxStorageBufferRange / 4;
  if (capacity > max_elements) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "vulkan: ", capacity, " tile instances exceed the device's storage buffer range (",
        max_elements, " elements)"));
  }
  // Values exist only in pair mode (stages.h: RankBits).
  const bool pairs = rank_bits(n, width, height) == 0;
  uint64_t capacity_bytes = UINT64_MAX;
  for (int i = 0; i < 2; ++i) {
    for (Buffer* b : {&inst_keys_[i], &inst_vals_[i]}) {
      if (b == &inst_vals_[i] && !pairs) continue;
      if (absl::Status s = EnsureBufferCapacity(c, b, capacity * 4, Buffer::Kind::kDevice, "instances");
          !s.ok()) {
        return s;
      }
      capacity_bytes = std::min(capacity_bytes, b->size());
    }
  }
  instance_capacity_ = std::min(capacity_bytes / 4, max_elements);
  const uint64_t sort_max = std::max<uint64_t>(n, instance_capacity_);
  const uint64_t hist_elements = kRadix * DivUp(sort_max, kSortBlock);
  if (absl::Status s = EnsureBufferCapacity(c, &hist_, hist_elements * 4, Buffer::Kind::kDevice, "hist");
      !s.ok()) {
    return s;
  }
  if (absl::Status s = scratch_.Ensure(c, std::max<uint64_t>(n, hist_elements)); !s.ok()) return s;

  const uint64_t pixels = uint64_t{width} * height;
  const uint64_t tiles = DivUp(width, kTileSize) * DivUp(height, kTileSize);
  for (auto [buffer, bytes, name] :
       {std::tuple{&ranges_, tiles * 8, "ranges"}, std::tuple{&rgb_, pixels * 12, "rgb"},
        std::tuple{&depth_, pixels * 4, "depth"}, std::tuple{&alpha_, pixels * 4, "alpha"},
        std::tuple{&final_t_, pixels * 4, "final_t"},
        std::tuple{&n_contrib_, pixels * 4, "n_contrib"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, Buffer::Kind::kDevice, name); !s.ok()) {
      return s;
    }
  }
  return EnsureBufferCapacity(c, &readback_, kCountsBytes + pixels * 20, Buffer::Kind::kReadback,
                      "readback");
}

absl::Status VulkanEngine::SubmitAndWait(Recorder& rec, Buffer& readback) {
  return SubmitFrameAndWait(*ctx_, rec, fence_, readback, profiler_.get());
}

absl::Status VulkanEngine::RenderOnce(const VulkanScene& scene, const PinholeCamera& camera,
                                      const RenderOptions& options, uint32_t* counts) {
  const Context& c = *ctx_;
  const uint32_t n = static_cast<uint32_t>(scene.size());
  const uint32_t width = camera.width, height = camera.height;
  const uint32_t tiles_x = DivUp(width, kTileSize), tiles_y = DivUp(height, kTileSize);
  const VkDeviceSize pixels = VkDeviceSize{width} * height;

  if (absl::Status s = BeginFrameCommands(cmd_, *arena_); !s.ok()) return s;
  Recorder rec(c, cmd_, arena_.get());
  AttachProfiler(rec, profiler_.get());
  auto timestamp = [&](uint32_t index) {
    if (query_pool_ != VK_NULL_HANDLE) {
      vkCmdWriteTimestamp(cmd_, VK_PIPELINE_STAGE_BOTTOM_OF_PIPE_BIT, query_pool_, index);
    }
  };
  if (query_pool_ != VK_NULL_HANDLE) vkCmdResetQueryPool(cmd_, query_pool_, 0, kNumTimestamps);
  uint32_t initial_counts[kNumCounts] = {};
  initial_counts[kCountN] = n;
  rec.Update(counts_, 0, initial_counts);
  rec.Fill(ranges_, 0, VkDeviceSize{tiles_x} * tiles_y * 8, 0);
  rec.Barrier();
  timestamp(0);

  const SceneBuffers sb = scene.view();
  const ProjectPush project_push = MakeProjectPush(camera, n, scene.sh_degree());
  RecordProjectAndCompact(rec, *kernels_, scratch_, sb, counts_, args_, project_push);
  timestamp(1);
  const BinningBuffers bins{
      {&inst_keys_[0], &inst_keys_[1]}, {&inst_vals_[0], &inst_vals_[1]}, &hist_, &ranges_};
  const BinningResult sorted =
      RecordSortAndBin(rec, *kernels_, scratch_, sb, bins, counts_, args_, n, instance_capacity_,
                       tiles_x, tiles_y, rank_bits(n, width, height));
  timestamp(2);
  const BlendParams blend{width,
                          height,
                          tiles_x,
                          tiles_y,
                          {options.background.x(), options.background.y(), options.background.z()}};
  RecordBlend(rec, *kernels_, ranges_, sorted, *sb.sorted_splats,
              ImageBuffers{&rgb_, &depth_, &alpha_, &final_t_, &n_contrib_}, blend);
  // The blend always writes final T and n_contrib; a backward pass needs only what was recorded.
  if (options.keep_for_backward) kept_ = Kept{nullptr, project_push, blend, sorted};
  timestamp(3);

  // Readback layout: counts | rgb | depth | alpha; only what the caller wants is copied.
  rec.Copy(counts_, 0, readback_, 0, kCountsBytes);
  rec.Copy(rgb_, 0, readback_, kCountsBytes, pixels * 12);
  if (options.want_depth) rec.Copy(depth_, 0, readback_, kCountsBytes + pixels * 12, pixels * 4);
  if (options.want_alpha) rec.Copy(alpha_, 0, readback_, kCountsBytes + pixels * 16, pixels * 4);
  if (absl::Status s = SubmitAndWait(rec, readback_); !s.ok()) return s;
  std::memcpy(counts, readback_.mapped(), kCountsBytes);
  return absl::OkStatus();
}

absl::Status VulkanEngine::Render(const DeviceScene& scene, const PinholeCamera& camera,
                                  const RenderOptions& options, RenderOutput* out) {
  const auto start = std::chrono::steady_clock::now();
  if (out == nullptr) return absl::InvalidArgumentError("vulkan: Render: out is null");
  if (absl::Status s = camera.Validate(); !s.ok()) return s;
  const auto* vscene = dynamic_cast<const VulkanScene*>(&scene);
  if (vscene == nullptr || vscene->engine_id() != id_) {
    return absl::InvalidArgumentError(
        "vulkan: Render: the scene was not uploaded by this vulkan engine");
  }
  std::lock_guard<std::mutex> lock(mu_);
  kept_.scene = nullptr;
  const uint32_t n = static_cast<uint32_t>(vscene->size());
  // Instance capacity from an estimate; the device clamps its writes to it, and the rare frame
  // that needs more is rendered again with room for all of them.
  const uint64_t max_instances = ctx_->limits().maxStorageBufferRange / 4;
  uint64_t capacity = std::min(
      max_instances, std::max<uint64_t>({uint64_t{4} * n, last_instances_ + last_instances_ / 4,
                                         kMinInstanceCapacity, instance_capacity_}));
  uint32_t counts[kNumCounts] = {};
  // The frame is one submission: a caller who gave up is heard before it and before the readback.
  const auto stopped = [&] { return options.should_stop && options.should_stop(); };
  for (int attempt = 0;; ++attempt) {
    if (stopped()) return absl::CancelledError("vulkan: render stopped by its caller");
    if (absl::Status s = EnsureFrameResources(n, camera.width, camera.height, capacity); !s.ok()) {
      return s;
    }
    if (absl::Status s = RenderOnce(*vscene, camera, options, counts); !s.ok()) return s;
    const uint64_t instances = counts[kCountI];
    if (instances <= instance_capacity_) break;
    if (instances > max_instances) {
      return absl::ResourceExhaustedError(
          absl::StrCat("vulkan: the frame needs ",
                       instances == UINT32_MAX ? "2^32 or more" : absl::StrCat(instances),
                       " tile instances; the device's storage buffer range holds ", max_instances));
    }
    if (attempt > 0) {
      return absl::InternalError(absl::StrCat("vulkan: ", instances,
                                              " tile instances still exceed the capacity ",
                                              instance_capacity_, " after growing"));
    }
    LOG(INFO) << "vulkan: " << instances << " tile instances exceed the capacity "
              << instance_capacity_ << "; growing and rendering the frame again";
    capacity = std::min(instances + instances / 4, max_instances);
    ++rerenders_;
  }
  last_instances_ = counts[kCountI];
  if (options.keep_for_backward) {
    kept_.scene = vscene;
    kept_.instances = counts[kCountI];
  }

  if (stopped()) return absl::CancelledError("vulkan: render stopped by its caller");
  if (absl::Status s = Readback(camera, options, out); !s.ok()) return s;
  out->stats.num_gaussians = n;
  out->stats.num_visible = counts[kCountV];
  out->stats.num_tile_instances = counts[kCountI];
  out->timings = StageTimings{};
  if (query_pool_ != VK_NULL_HANDLE) {
    uint64_t ticks[kNumTimestamps] = {};
    const VkResult r =
        vkGetQueryPoolResults(ctx_->device(), query_pool_, 0, kNumTimestamps, sizeof(ticks), ticks,
                              sizeof(uint64_t), VK_QUERY_RESULT_64_BIT | VK_QUERY_RESULT_WAIT_BIT);
    if (r == VK_SUCCESS) {
      const uint32_t bits = ctx_->timestamp_valid_bits();
      const uint64_t mask = bits >= 64 ? ~uint64_t{0} : (uint64_t{1} << bits) - 1;
      auto ms = [&](int a, int b) {
        return static_cast<double>((ticks[b] - ticks[a]) & mask) * ctx_->timestamp_period_ns() *
               1e-6;
      };
      out->timings.projection_ms = ms(0, 1);
      out->timings.sort_ms = ms(1, 2);
      out->timings.blend_ms = ms(2, 3);
    }
  }
  out->timings.total_ms = MsSince(start);
  return absl::OkStatus();
}

absl::Status VulkanEngine::Readback(const PinholeCamera& camera, const RenderOptions& options,
                                    RenderOutput* out) {
  const size_t pixels = size_t{static_cast<size_t>(camera.width)} * camera.height;
  const auto* base = static_cast<const std::byte*>(readback_.mapped());
  out->width = camera.width;
  out->height = camera.height;
  out->rgb.resize(pixels * 3);
  std::memcpy(out->rgb.data(), base + kCountsBytes, pixels * 12);
  out->depth.resize(options.want_depth ? pixels : 0);
  if (options.want_depth) {
    std::memcpy(out->depth.data(), base + kCountsBytes + pixels * 12, pixels * 4);
  }
  out->alpha.resize(options.want_alpha ? pixels : 0);
  if (options.want_alpha) {
    std::memcpy(out->alpha.data(), base + kCountsBytes + pixels * 16, pixels * 4);
  }
  return absl::OkStatus();
}

absl::Status VulkanEngine::UpdateScene(const GaussianStore& store,
                                       std::unique_ptr<DeviceScene>* scene) {
  auto* vscene = scene->get() ? dynamic_cast<VulkanScene*>(scene->get()) : nullptr;
  if (vscene == nullptr || vscene->engine_id() != id_ || vscene->size() != store.size() ||
      vscene->sh_degree() != store.sh_degree) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (kept_.scene == vscene) kept_.scene = nullptr;
    }
    return Engine::UpdateScene(store, scene);
  }
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  std::lock_guard<std::mutex> lock(mu_);
  if (kept_.scene == vscene) kept_.scene = nullptr;  // the kept splats no longer match
  return UploadParams(store, vscene);
}

absl::Status VulkanEngine::WriteSceneOnDevice(
    DeviceScene* scene, const std::function<void(Recorder&, const VulkanScene&)>& record) {
  auto* vscene = scene ? dynamic_cast<VulkanScene*>(scene) : nullptr;
  if (vscene == nullptr || vscene->engine_id() != id_) {
    return absl::InvalidArgumentError("vulkan: WriteSceneOnDevice: not a scene of this engine");
  }
  std::lock_guard<std::mutex> lock(mu_);
  if (kept_.scene == vscene) kept_.scene = nullptr;  // the kept splats no longer match
  if (absl::Status s = BeginFrameCommands(cmd_, *arena_); !s.ok()) return s;
  Recorder rec(*ctx_, cmd_, arena_.get());
  AttachProfiler(rec, profiler_.get());
  record(rec, *vscene);
  rec.Barrier();  // the next frame's projection reads what was written
  return SubmitAndWait(rec, readback_);
}

absl::Status VulkanEngine::EnsureBackwardResources(const VulkanScene& scene, uint32_t pixels) {
  const Context& c = *ctx_;
  const VkDeviceSize n = scene.size();
  const int K = (scene.sh_degree() + 1) * (scene.sh_degree() + 1);
  VkDeviceSize sh_bytes = 0;
  for (int g = 0; g < kMaxShGroups; ++g) {
    const VkDeviceSize bytes = n * ShGroupFloats(K, g) * 4;
    sh_bytes += bytes;
    if (g == 0 || bytes > 0) {
      if (absl::Status s = EnsureBufferCapacity(c, &sh_grads_[g], bytes, Buffer::Kind::kDevice, "sh_grads");
          !s.ok()) {
        return s;
      }
    }
  }
  for (auto [buffer, bytes, kind, name] :
       {std::tuple{&pixel_grads_, VkDeviceSize{pixels} * 20, Buffer::Kind::kDevice, "pixel_grads"},
        std::tuple{&pixel_grads_staging_, VkDeviceSize{pixels} * 20, Buffer::Kind::kStaging,
                   "pixel_grads_staging"},
        std::tuple{&splat_grads_, n * kSplatGradFloats * 4, Buffer::Kind::kDevice, "splat_grads"},
        std::tuple{&param_grads_, n * kParamGradFloats * 4, Buffer::Kind::kDevice, "param_grads"},
        std::tuple{&bwd_readback_, n * kParamGradFloats * 4 + sh_bytes, Buffer::Kind::kReadback,
                   "bwd_readback"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, kind, name); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::Status VulkanEngine::RenderBackward(const DeviceScene& scene, const RenderOutputGrads& grads,
                                          const BackwardOptions& options, GaussianGrads* out) {
  const auto start = std::chrono::steady_clock::now();
  if (out == nullptr) return absl::InvalidArgumentError("vulkan: RenderBackward: out is null");
  if (grads.rgb == nullptr) {
    return absl::InvalidArgumentError("vulkan: RenderBackward: dL/drgb is required");
  }
  std::lock_guard<std::mutex> lock(mu_);
  const auto* vscene = dynamic_cast<const VulkanScene*>(&scene);
  if (vscene == nullptr || vscene != kept_.scene) {
    return absl::FailedPreconditionError(
        "vulkan: RenderBackward needs the last Render of this scene on this engine with "
        "keep_for_backward");
  }
  if (kernels_->blend_backward == nullptr) {
    return absl::FailedPreconditionError(absl::StrCat(
        device_name(), ": the backward pass needs subgroup arithmetic operations"));
  }
  const Context& c = *ctx_;
  const uint32_t n = static_cast<uint32_t>(vscene->size());
  const int K = (vscene->sh_degree() + 1) * (vscene->sh_degree() + 1);
  const size_t pixels = size_t{kept_.blend.width} * kept_.blend.height;
  if (absl::Status s = EnsureBackwardResources(*vscene, static_cast<uint32_t>(pixels)); !s.ok()) {
    return s;
  }
  // Deterministic mode: one slot of kDetSlotFloats per tile instance of the kept frame.
  uint64_t det_slot_capacity = 0;
  if (options.deterministic) {
    if (absl::Status s = EnsureDeterministicKernels(c, kernels_.get()); !s.ok()) return s;
    const uint64_t limit = det_slot_limit_bytes_ > 0 ? det_slot_limit_bytes_
                                                     : uint64_t{c.limits().maxStorageBufferRange};
    const uint64_t slot_bytes = std::max<uint64_t>(kept_.instances, 1) * kDetSlotFloats * 4;
    if (slot_bytes > limit) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "vulkan: the deterministic backward needs ", slot_bytes, " bytes of slots for ",
          kept_.instances, " tile instances, more than the storage buffer range of ", limit,
          " bytes; render fewer tile instances or use the default (atomic) backward"));
    }
    if (absl::Status s = EnsureBufferCapacity(c, &det_slots_, slot_bytes, Buffer::Kind::kDevice,
                                      "det_slots");
        !s.ok()) {
      return s;
    }
    det_slot_capacity = slot_bytes / (kDetSlotFloats * 4);  // what the frame uses
  }
  // dL/d(outputs) into the staging buffer: rgb | depth | alpha, zeros for a null pointer.
  auto* staging = static_cast<float*>(pixel_grads_staging_.mapped());
  std::memcpy(staging, grads.rgb, pixels * 12);
  for (auto [src, offset] : {std::pair{grads.depth, pixels * 3}, std::pair{grads.alpha, pixels * 4}}) {
    if (src != nullptr) {
      std::memcpy(staging + offset, src, pixels * 4);
    } else {
      std::memset(staging + offset, 0, pixels * 4);
    }
  }

  if (absl::Status s = BeginFrameCommands(cmd_, *arena_); !s.ok()) return s;
  Recorder rec(c, cmd_, arena_.get());
  AttachProfiler(rec, profiler_.get());
  rec.Copy(pixel_grads_staging_, 0, pixel_grads_, 0, pixels * 20);
  BackwardBuffers bwd{&pixel_grads_, &splat_grads_, &param_grads_, {}, {},
                      options.deterministic ? &det_slots_ : nullptr, det_slot_capacity};
  VkDeviceSize sh_offsets[kMaxShGroups] = {};
  VkDeviceSize offset = VkDeviceSize{n} * kParamGradFloats * 4;
  for (int g = 0; g < kMaxShGroups; ++g) {
    bwd.sh_grad_bytes[g] = VkDeviceSize{n} * ShGroupFloats(K, g) * 4;
    bwd.sh_grads[g] = bwd.sh_grad_bytes[g] > 0 ? &sh_grads_[g] : &sh_grads_[0];
    sh_offsets[g] = offset;
    offset += bwd.sh_grad_bytes[g];
  }
  const SceneBuffers sb = vscene->view();
  RecordBackward(rec, *kernels_, sb, ranges_, kept_.bins,
                 ImageBuffers{&rgb_, &depth_, &alpha_, &final_t_, &n_contrib_}, kept_.blend,
                 counts_, args_, kept_.push, bwd);
  rec.Copy(param_grads_, 0, bwd_readback_, 0, VkDeviceSize{n} * kParamGradFloats * 4);
  for (int g = 0; g < kMaxShGroups; ++g) {
    if (bwd.sh_grad_bytes[g] > 0) {
      rec.Copy(sh_grads_[g], 0, bwd_readback_, sh_offsets[g], bwd.sh_grad_bytes[g]);
    }
  }
  if (absl::Status s = SubmitAndWait(rec, bwd_readback_); !s.ok()) return s;

  // Unpack into the GaussianStore layouts.
  const auto* base = static_cast<const std::byte*>(bwd_readback_.mapped());
  const float* pg = reinterpret_cast<const float*>(base);
  out->means.resize(size_t{n} * 3);
  out->log_scales.resize(size_t{n} * 3);
  out->rotations.resize(size_t{n} * 4);
  out->opacity_logits.resize(n);
  out->sh.resize(size_t{n} * K * 3);
  out->means2d.resize(size_t{n} * 2);
  out->radii.resize(n);
  // In parallel: on a GPU this unpacking, not the kernels, was most of the backward's time.
  if (host_pool_ == nullptr) host_pool_ = std::make_unique<ThreadPool>(0);
  host_pool_->ParallelFor(n, 8192, [&](int64_t i0, int64_t i1, int) {
    for (size_t i = static_cast<size_t>(i0); i < static_cast<size_t>(i1); ++i) {
      const float* p = pg + i * kParamGradFloats;
      std::memcpy(&out->means[i * 3], p, 12);
      out->opacity_logits[i] = p[3];
      std::memcpy(&out->log_scales[i * 3], p + 4, 12);
      out->radii[i] = p[7];
      std::memcpy(&out->rotations[i * 4], p + 8, 16);
      std::memcpy(&out->means2d[i * 2], p + 12, 8);
    }
    for (int g = 0; g < kMaxShGroups; ++g) {
      const size_t floats = ShGroupFloats(K, g);
      if (floats == 0) continue;
      const float* src = reinterpret_cast<const float*>(base + sh_offsets[g]);
      for (size_t i = static_cast<size_t>(i0); i < static_cast<size_t>(i1); ++i) {
        std::memcpy(&out->sh[(i * K + g * kShGroup) * 3], src + i * floats, floats * 4);
      }
    }
  });
  out->backward_ms = MsSince(start);
  return absl::OkStatus();
}

}  // namespace vulkan

absl::StatusOr<std::unique_ptr<Engine>> CreateVulkanEngine(VulkanDevicePreference pref) {
  auto engine = vulkan::VulkanEngine::Create(pref);
  if (!engine.ok()) return engine.status();
  return std::unique_ptr<Engine>(std::move(*engine));
}

}  // namespace streetsim
