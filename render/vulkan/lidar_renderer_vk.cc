// VulkanLidarRenderer: scene upload, per-sweep host tables, the one command buffer of a sweep
// (stages in lidar_stages_vk.cc) and the readback into LidarRenderOutput.
#include "render/vulkan/lidar_renderer_vk.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <string_view>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/lidar_backward_vk.h"
#include "render/vulkan/lidar_stages_vk.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/stages.h"

namespace streetsim {

namespace vk = vulkan;

namespace {

constexpr uint32_t kNumTimestamps = 4;
constexpr VkDeviceSize kCountsBytes = vk::kNumCounts * sizeof(uint32_t);
constexpr uint64_t kMinInstanceCapacity = 1 << 14;
constexpr int kPlanes = 5;                        // lidar_blend.comp's output planes
constexpr size_t kMaxGaussians = size_t{1} << 26;  // as the camera path (2^27 entries)
constexpr float kNearM = 0.2f;                     // render/lidar: lidar::kNearM

using vk::EnsureBufferCapacity;

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

// The sweep table of lidar_common.glsl: beam elevations (radians) and segment slopes as the cpu's
// vectorised kernel rounds them (lidar_renderer.cc: BeamTableFloat), then the pose(s).
void FillSweepTable(const LidarModel& model, const LidarSweepPose& sweep, float* table,
                    uint32_t* pose_offset) {
  const int B = model.beams();
  for (int b = 0; b < B; ++b) table[b] = static_cast<float>(model.BeamElevationRad(b));
  for (int k = 0; k + 1 < B; ++k) {
    table[B + k] = static_cast<float>(1.0 / (model.BeamElevationRad(k + 1) - model.BeamElevationRad(k)));
  }
  *pose_offset = static_cast<uint32_t>(2 * B);
  float* poses = table + *pose_offset;
  std::vector<double> columns;
  if (sweep.is_static()) {
    ColumnPoseTable(sweep, 1, &columns);  // one entry: T_world_from_lidar_start.inverse()
  } else {
    ColumnPoseTable(sweep, model.columns, &columns);
  }
  for (size_t k = 0; k < columns.size(); ++k) poses[k] = static_cast<float>(columns[k]);
}

size_t SweepTableFloats(const LidarModel& model) {
  return 2 * static_cast<size_t>(model.beams()) + static_cast<size_t>(model.columns) * 12;
}

}  // namespace

struct VulkanLidarRenderer::Impl {
  // Declared first: destroyed last, after every buffer and pipeline of its device.
  std::unique_ptr<vk::Context> ctx;
  std::unique_ptr<vk::LidarKernels> kernels;
  std::unique_ptr<vk::DescriptorArena> arena;
  VkCommandBuffer cmd = VK_NULL_HANDLE;
  VkFence fence = VK_NULL_HANDLE;
  VkQueryPool query_pool = VK_NULL_HANDLE;
  std::unique_ptr<vk::Profiler> profiler;  // STREETSIM_VK_PROFILE=1: per-dispatch times at INFO

  vk::ScanScratch scratch;
  // The scene (Upload) and its per-Gaussian / per-entry working buffers.
  bool uploaded = false;
  uint32_t n = 0;
  vk::Buffer gauss, splats, rects, flags, touched, touched_sorted;
  std::array<vk::Buffer, 2> keys, ids;
  // Per sweep.
  vk::Buffer table, table_staging, refl, refl_staging;
  vk::Buffer sorted_splats, counts, args, hist, ranges, planes, readback;
  std::array<vk::Buffer, 2> inst_keys, inst_vals;
  uint64_t instance_capacity = 0, last_instances = 0;
  uint32_t splat_capacity = 0, last_visible = 0;
  int rerenders = 0;
  // Backward: per-ray state (written by every sweep), upstream gradients, accumulators, results.
  vk::Buffer ray_state, ray_grads, ray_grads_staging, splat_grads, param_grads, bwd_readback;
  vk::Buffer det_slots, det_rank_of;  // deterministic Backward (lidar_backward_vk.h)
  // What Backward needs from the last sweep with keep_for_backward (its buffers stay untouched
  // until the next Render or Upload, which clear `valid`).
  struct Kept {
    bool valid = false;
    vk::LidarProjectPush project{};
    vk::LidarBlendPush blend{};
    vk::BinningResult bins{};
    uint64_t instances = 0;  // I of the kept sweep (sizes the deterministic backward's slots)
  } kept;
  std::mutex mu;

  ~Impl() {
    if (!ctx) return;
    VkDevice device = ctx->device();
    vkDeviceWaitIdle(device);
    if (query_pool != VK_NULL_HANDLE) vkDestroyQueryPool(device, query_pool, nullptr);
    if (fence != VK_NULL_HANDLE) vkDestroyFence(device, fence, nullptr);
    if (cmd != VK_NULL_HANDLE) vkFreeCommandBuffers(device, ctx->command_pool(), 1, &cmd);
  }

  vk::LidarFrameBuffers Frame(bool has_refl) const {
    return vk::LidarFrameBuffers{&gauss,
                                 &table,
                                 has_refl ? &refl : &gauss,
                                 &splats,
                                 &sorted_splats,
                                 &rects,
                                 &flags,
                                 &touched,
                                 &touched_sorted,
                                 {&keys[0], &keys[1]},
                                 {&ids[0], &ids[1]},
                                 {&inst_keys[0], &inst_keys[1]},
                                 {&inst_vals[0], &inst_vals[1]},
                                 &hist,
                                 &ranges,
                                 &planes,
                                 &ray_state};
  }

  absl::Status EnsureSweepResources(const LidarModel& model, bool has_refl, uint64_t want_instances,
                                    uint32_t want_splats);
  absl::Status RecordAndSubmit(const LidarModel& model, const vk::LidarProjectPush& project,
                               const vk::LidarBlendPush& blend, uint32_t* counts_out,
                               vk::BinningResult* bins_out);
  absl::Status Backward(const LidarUpstreamGrads& upstream, LidarGaussianGrads* grads,
                        bool deterministic);
  absl::Status Render(const LidarModel& model, const LidarSweepPose& sweep,
                      const LidarRenderOptions& options, LidarRenderOutput* out);
};

absl::StatusOr<std::unique_ptr<VulkanLidarRenderer>> VulkanLidarRenderer::Create(
    VulkanDevicePreference preference) {
  auto impl = std::make_unique<Impl>();
  auto ctx = vk::Context::Create(preference);
  if (!ctx.ok()) return ctx.status();
  impl->ctx = *std::move(ctx);
  const vk::Context& c = *impl->ctx;
  auto kernels = vk::LidarKernels::Create(c);
  if (!kernels.ok()) return kernels.status();
  impl->kernels = *std::move(kernels);
  impl->arena = std::make_unique<vk::DescriptorArena>(c.device());
  if (absl::Status s = vk::CreateFrameObjects(c, kNumTimestamps, &impl->cmd, &impl->fence, &impl->query_pool,
                                              &impl->profiler);
      !s.ok()) {
    return s;
  }
  for (auto [buffer, bytes, name] :
       {std::tuple{&impl->counts, kCountsBytes, "lidar_counts"},
        std::tuple{&impl->args, VkDeviceSize{vk::kNumArgs * vk::kArgsSlotBytes}, "lidar_args"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, vk::Buffer::Kind::kDevice, name); !s.ok()) {
      return s;
    }
  }
  return std::unique_ptr<VulkanLidarRenderer>(new VulkanLidarRenderer(std::move(impl)));
}

VulkanLidarRenderer::VulkanLidarRenderer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
VulkanLidarRenderer::~VulkanLidarRenderer() = default;

std::string VulkanLidarRenderer::device_name() const { return impl_->ctx->description(); }

int VulkanLidarRenderer::rerenders() const {
  std::lock_guard<std::mutex> lock(impl_->mu);
  return impl_->rerenders;
}

size_t VulkanLidarRenderer::uploaded_size() const {
  std::lock_guard<std::mutex> lock(impl_->mu);
  return impl_->uploaded ? impl_->n : 0;
}

absl::Status VulkanLidarRenderer::Upload(const GaussianStore& store) {
  Impl& w = *impl_;
  std::lock_guard<std::mutex> lock(w.mu);
  w.uploaded = false;
  w.kept.valid = false;
  w.n = 0;
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  const size_t n = store.size();
  if (n > kMaxGaussians) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan LiDAR: ", n,
                                                   " Gaussians exceed the limit of ", kMaxGaussians));
  }
  const vk::Context& c = *w.ctx;
  const VkDeviceSize n64 = n, entries = 2 * n64;
  struct Alloc {
    vk::Buffer* buffer;
    VkDeviceSize bytes;
    const char* name;
  };
  for (const Alloc& a : {Alloc{&w.gauss, n64 * 48, "lidar_gauss"}, Alloc{&w.splats, n64 * 48, "lidar_splats"},
                         Alloc{&w.rects, entries * 8, "lidar_rects"},
                         Alloc{&w.flags, entries * 4, "lidar_flags"},
                         Alloc{&w.touched, entries * 4, "lidar_touched"},
                         Alloc{&w.touched_sorted, entries * 4, "lidar_touched_sorted"},
                         Alloc{&w.keys[0], entries * 4, "lidar_keys0"},
                         Alloc{&w.keys[1], entries * 4, "lidar_keys1"},
                         Alloc{&w.ids[0], entries * 4, "lidar_ids0"},
                         Alloc{&w.ids[1], entries * 4, "lidar_ids1"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, a.buffer, a.bytes, vk::Buffer::Kind::kDevice, a.name); !s.ok()) {
      return s;
    }
  }
  absl::Status s = vk::UploadGaussianGeometry(c, w.gauss, store);
  if (!s.ok()) return s;
  w.n = static_cast<uint32_t>(n);
  w.uploaded = true;
  w.last_instances = 0;
  w.last_visible = 0;
  return absl::OkStatus();
}

absl::Status VulkanLidarRenderer::Impl::EnsureSweepResources(const LidarModel& model, bool has_refl,
                                                            uint64_t want_instances,
                                                            uint32_t want_splats) {
  const vk::Context& c = *ctx;
  const uint64_t max_elements = c.limits().maxStorageBufferRange / 4;
  const uint32_t tiles = vk::DivUp(model.columns, vk::kTileSize) * vk::DivUp(model.beams(), vk::kTileSize);
  const bool pairs = vk::RankBits(2 * n, tiles) == 0;
  uint64_t capacity_bytes = UINT64_MAX;
  for (int i = 0; i < 2; ++i) {
    for (vk::Buffer* b : {&inst_keys[i], &inst_vals[i]}) {
      if (b == &inst_vals[i] && !pairs) continue;
      if (absl::Status s = EnsureBufferCapacity(c, b, want_instances * 4, vk::Buffer::Kind::kDevice, "lidar_instances");
          !s.ok()) {
        return s;
      }
      capacity_bytes = std::min(capacity_bytes, b->size());
    }
  }
  instance_capacity = std::min(capacity_bytes / 4, max_elements);
  if (absl::Status s = EnsureBufferCapacity(c, &sorted_splats, VkDeviceSize{want_splats} * 48,
                                    vk::Buffer::Kind::kDevice, "lidar_sorted_splats");
      !s.ok()) {
    return s;
  }
  splat_capacity = static_cast<uint32_t>(std::min<VkDeviceSize>(sorted_splats.size() / 48, 2 * VkDeviceSize{n}));
  splat_capacity = std::max<uint32_t>(splat_capacity, 1);
  const uint64_t sort_max = std::max<uint64_t>(2 * uint64_t{n}, instance_capacity);
  const uint64_t hist_elements = vk::kRadix * vk::DivUp(sort_max, vk::kSortBlock);
  if (absl::Status s = EnsureBufferCapacity(c, &hist, hist_elements * 4, vk::Buffer::Kind::kDevice, "lidar_hist");
      !s.ok()) {
    return s;
  }
  if (absl::Status s = scratch.Ensure(c, std::max<uint64_t>(2 * uint64_t{n}, hist_elements)); !s.ok()) {
    return s;
  }
  const VkDeviceSize rays = VkDeviceSize{static_cast<uint64_t>(model.beams())} * model.columns;
  const VkDeviceSize table_bytes = SweepTableFloats(model) * 4;
  const VkDeviceSize refl_bytes = has_refl ? VkDeviceSize{n} * 4 : 0;
  for (auto [buffer, bytes, kind, name] :
       {std::tuple{&ranges, VkDeviceSize{tiles} * 8, vk::Buffer::Kind::kDevice, "lidar_ranges"},
        std::tuple{&planes, rays * kPlanes * 4, vk::Buffer::Kind::kDevice, "lidar_planes"},
        std::tuple{&ray_state, rays * 8, vk::Buffer::Kind::kDevice, "lidar_ray_state"},
        std::tuple{&readback, kCountsBytes + rays * kPlanes * 4, vk::Buffer::Kind::kReadback, "lidar_readback"},
        std::tuple{&table, table_bytes, vk::Buffer::Kind::kDevice, "lidar_table"},
        std::tuple{&table_staging, table_bytes, vk::Buffer::Kind::kStaging, "lidar_table_staging"},
        std::tuple{&refl, refl_bytes, vk::Buffer::Kind::kDevice, "lidar_reflectance"},
        std::tuple{&refl_staging, refl_bytes, vk::Buffer::Kind::kStaging, "lidar_reflectance_staging"}}) {
    if (bytes == 0 && (buffer == &refl || buffer == &refl_staging)) continue;
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, kind, name); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::Status VulkanLidarRenderer::Impl::RecordAndSubmit(const LidarModel& model,
                                                        const vk::LidarProjectPush& project,
                                                        const vk::LidarBlendPush& blend,
                                                        uint32_t* counts_out,
                                                        vk::BinningResult* bins_out) {
  const vk::Context& c = *ctx;
  const uint32_t tiles_x = project.tiles_x, tiles_y = project.tiles_y;
  const VkDeviceSize rays = VkDeviceSize{static_cast<uint64_t>(model.beams())} * model.columns;
  if (absl::Status s = vk::BeginFrameCommands(cmd, *arena); !s.ok()) return s;
  vk::Recorder rec(c, cmd, arena.get());
  vk::AttachProfiler(rec, profiler.get());
  auto timestamp = [&](uint32_t index) {
    if (query_pool != VK_NULL_HANDLE) {
      vkCmdWriteTimestamp(cmd, VK_PIPELINE_STAGE_BOTTOM_OF_PIPE_BIT, query_pool, index);
    }
  };
  if (query_pool != VK_NULL_HANDLE) vkCmdResetQueryPool(cmd, query_pool, 0, kNumTimestamps);

  uint32_t initial_counts[vk::kNumCounts] = {};
  initial_counts[vk::kCountN] = 2 * n;  // entries: a splat and its seam copy per Gaussian
  rec.Update(counts, 0, initial_counts);
  rec.Fill(ranges, 0, VkDeviceSize{tiles_x} * tiles_y * 8, 0);
  rec.Copy(table_staging, 0, table, 0, SweepTableFloats(model) * 4);
  if (project.has_refl != 0) rec.Copy(refl_staging, 0, refl, 0, VkDeviceSize{n} * 4);
  rec.Barrier();
  timestamp(0);

  const vk::LidarFrameBuffers f = Frame(project.has_refl != 0);
  vk::RecordLidarProject(rec, *kernels, scratch, f, counts, args, project);
  timestamp(1);
  const vk::BinningResult bins = vk::RecordLidarSortAndBin(
      rec, *kernels, scratch, f, counts, args, 2 * n, instance_capacity, splat_capacity,
      vk::LidarRangeKeyBits(project.near_m, project.far_m), tiles_x, tiles_y,
      vk::RankBits(2 * n, tiles_x * tiles_y));
  timestamp(2);
  vk::LidarBlendPush bp = blend;
  bp.splat_capacity = splat_capacity;
  vk::RecordLidarBlend(rec, *kernels, f, bins, bp, tiles_y);
  *bins_out = bins;
  timestamp(3);
  rec.Copy(counts, 0, readback, 0, kCountsBytes);
  rec.Copy(planes, 0, readback, kCountsBytes, rays * kPlanes * 4);
  if (absl::Status s = vk::SubmitFrameAndWait(c, rec, fence, readback, profiler.get()); !s.ok()) return s;
  std::memcpy(counts_out, readback.mapped(), kCountsBytes);
  return absl::OkStatus();
}

absl::Status VulkanLidarRenderer::Impl::Render(const LidarModel& model, const LidarSweepPose& sweep,
                                               const LidarRenderOptions& options,
                                               LidarRenderOutput* out) {
  const auto start = std::chrono::steady_clock::now();
  if (out == nullptr) return absl::InvalidArgumentError("VulkanLidarRenderer: out is null");
  std::lock_guard<std::mutex> lock(mu);
  kept.valid = false;  // this sweep overwrites the kept one's buffers
  if (!uploaded) return absl::InvalidArgumentError("VulkanLidarRenderer: no scene uploaded");
  if (absl::Status s = model.Validate(); !s.ok()) return s;
  if (absl::Status s = ValidateSweepPose(sweep); !s.ok()) return s;
  if (options.reflectance && options.reflectance->size() != n) {
    return absl::InvalidArgumentError(absl::StrCat("reflectance has ", options.reflectance->size(),
                                                   " values for ", n, " Gaussians"));
  }
  const int B = model.beams(), W = model.columns;
  const uint64_t rays = static_cast<uint64_t>(B) * W;
  if (rays >= (uint64_t{1} << 31)) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan LiDAR: ", B, " x ", W, " rays are too many"));
  }
  const bool has_refl = options.reflectance != nullptr && n > 0;
  const uint32_t tiles_x = vk::DivUp(W, vk::kTileSize), tiles_y = vk::DivUp(B, vk::kTileSize);

  vk::LidarProjectPush project{};
  project.n = n;
  project.columns = W;
  project.beams = B;
  project.tiles_x = static_cast<int32_t>(tiles_x);
  project.tiles_y = static_cast<int32_t>(tiles_y);
  project.near_m = std::max(kNearM, static_cast<float>(model.min_range_m));
  project.far_m = static_cast<float>(model.max_range_m);
  project.cols_per_rad = static_cast<float>(W / (2 * M_PI));
  project.rolling = sweep.is_static() ? 0 : 1;
  project.has_refl = has_refl ? 1 : 0;
  vk::LidarBlendPush blend{};
  blend.columns = static_cast<uint32_t>(W);
  blend.beams = static_cast<uint32_t>(B);
  blend.tiles_x = tiles_x;
  blend.return_alpha_threshold = options.return_alpha_threshold;
  blend.sample_drop = options.sample_drop ? 1 : 0;
  blend.seed_lo = static_cast<uint32_t>(options.seed);
  blend.seed_hi = static_cast<uint32_t>(options.seed >> 32);

  // Capacities from estimates; the device clamps its writes to them, and the rare sweep that needs
  // more is recorded again with room for all (the counts are exact the second time).
  const uint64_t max_instances = ctx->limits().maxStorageBufferRange / 4;
  uint64_t want_instances = std::min(
      max_instances, std::max<uint64_t>({uint64_t{2} * n, last_instances + last_instances / 4,
                                         kMinInstanceCapacity, instance_capacity}));
  uint32_t want_splats = static_cast<uint32_t>(std::min<uint64_t>(
      2 * uint64_t{n}, std::max<uint64_t>({uint64_t{n} + n / 8, last_visible + last_visible / 4, 1024})));
  want_splats = std::max(want_splats, splat_capacity);
  uint32_t counts[vk::kNumCounts] = {};
  vk::BinningResult bins{};
  for (int attempt = 0;; ++attempt) {
    if (absl::Status s = EnsureSweepResources(model, has_refl, want_instances, want_splats); !s.ok()) {
      return s;
    }
    FillSweepTable(model, sweep, static_cast<float*>(table_staging.mapped()), &project.pose_offset);
    if (has_refl) std::memcpy(refl_staging.mapped(), options.reflectance->data(), size_t{n} * 4);
    if (absl::Status s = RecordAndSubmit(model, project, blend, counts, &bins); !s.ok()) return s;
    const uint64_t instances = counts[vk::kCountI];
    const uint32_t visible = counts[vk::kCountV];
    if (instances <= instance_capacity && visible <= splat_capacity) break;
    if (instances > max_instances) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "vulkan LiDAR: the sweep needs ", instances == UINT32_MAX ? "2^32 or more" : absl::StrCat(instances),
          " tile instances; the device's storage buffer range holds ", max_instances));
    }
    if (attempt > 0) {
      return absl::InternalError(absl::StrCat("vulkan LiDAR: ", instances, " tile instances / ", visible,
                                              " splats still exceed the capacities after growing"));
    }
    LOG(INFO) << "vulkan LiDAR: " << instances << " tile instances / " << visible
              << " splats exceed the capacities " << instance_capacity << " / " << splat_capacity
              << "; growing and rendering the sweep again";
    want_instances = std::min(std::max(want_instances, instances + instances / 4), max_instances);
    want_splats = std::max(want_splats, visible);
    ++rerenders;
  }
  last_instances = counts[vk::kCountI];
  last_visible = counts[vk::kCountV];
  if (options.keep_for_backward) {
    kept.valid = true;
    kept.project = project;
    kept.blend = blend;
    kept.blend.splat_capacity = splat_capacity;
    kept.blend.rank_mask = bins.rank_mask;
    kept.bins = bins;
    kept.instances = counts[vk::kCountI];
  }

  // Readback: counts | alpha | range_sum | intensity_sum | range | intensity.
  const size_t P = static_cast<size_t>(rays);
  const auto* planes_host =
      reinterpret_cast<const float*>(static_cast<const std::byte*>(readback.mapped()) + kCountsBytes);
  out->beams = B;
  out->columns = W;
  for (auto [plane, dst] : {std::pair{0, &out->alpha}, std::pair{1, &out->range_sum},
                            std::pair{2, &out->intensity_sum}, std::pair{3, &out->range},
                            std::pair{4, &out->intensity}}) {
    dst->resize(P);
    std::memcpy(dst->data(), planes_host + static_cast<size_t>(plane) * P, P * 4);
  }
  FillLidarPoints(model, options, out);
  out->num_gaussians = n;
  out->num_visible = counts[vk::kCountV];
  out->num_tile_instances = counts[vk::kCountI];
  out->projection_ms = out->sort_ms = out->blend_ms = 0;
  if (query_pool != VK_NULL_HANDLE) {
    uint64_t ticks[kNumTimestamps] = {};
    const VkResult r = vkGetQueryPoolResults(ctx->device(), query_pool, 0, kNumTimestamps, sizeof(ticks), ticks,
                                             sizeof(uint64_t), VK_QUERY_RESULT_64_BIT | VK_QUERY_RESULT_WAIT_BIT);
    if (r == VK_SUCCESS) {
      const uint32_t bits = ctx->timestamp_valid_bits();
      const uint64_t mask = bits >= 64 ? ~uint64_t{0} : (uint64_t{1} << bits) - 1;
      auto ms = [&](int a, int b) {
        return static_cast<double>((ticks[b] - ticks[a]) & mask) * ctx->timestamp_period_ns() * 1e-6;
      };
      out->projection_ms = ms(0, 1);
      out->sort_ms = ms(1, 2);
      out->blend_ms = ms(2, 3);
    }
  }
  out->total_ms = MsSince(start);
  return absl::OkStatus();
}

absl::Status VulkanLidarRenderer::Impl::Backward(const LidarUpstreamGrads& upstream,
                                                 LidarGaussianGrads* grads, bool deterministic) {
  if (grads == nullptr) return absl::InvalidArgumentError("VulkanLidarRenderer::Backward: grads is null");
  std::lock_guard<std::mutex> lock(mu);
  if (!kept.valid) {
    return absl::FailedPreconditionError(
        "VulkanLidarRenderer::Backward needs the last Render to have had keep_for_backward (and no "
        "Upload since)");
  }
  if (kernels->blend_backward == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat(ctx->description(), ": the LiDAR backward pass needs subgroup arithmetic operations"));
  }
  const vk::Context& c = *ctx;
  const size_t P = size_t{kept.blend.beams} * kept.blend.columns;
  for (auto [buffer, bytes, kind, name] :
       {std::tuple{&ray_grads, VkDeviceSize{P} * 12, vk::Buffer::Kind::kDevice, "lidar_ray_grads"},
        std::tuple{&ray_grads_staging, VkDeviceSize{P} * 12, vk::Buffer::Kind::kStaging,
                   "lidar_ray_grads_staging"},
        std::tuple{&splat_grads, VkDeviceSize{std::max<uint32_t>(n, 1)} * vk::kLidarSplatGradFloats * 4,
                   vk::Buffer::Kind::kDevice, "lidar_splat_grads"},
        std::tuple{&param_grads, VkDeviceSize{std::max<uint32_t>(n, 1)} * vk::kLidarParamGradFloats * 4,
                   vk::Buffer::Kind::kDevice, "lidar_param_grads"},
        std::tuple{&bwd_readback, VkDeviceSize{std::max<uint32_t>(n, 1)} * vk::kLidarParamGradFloats * 4,
                   vk::Buffer::Kind::kReadback, "lidar_bwd_readback"}}) {
    if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, kind, name); !s.ok()) return s;
  }
  // Deterministic mode: one slot of kLidarSplatGradFloats per tile instance of the kept sweep.
  uint64_t det_slot_capacity = 0;
  if (deterministic) {
    if (absl::Status s = vk::EnsureLidarDeterministicKernels(c, kernels.get()); !s.ok()) return s;
    const uint64_t limit = c.limits().maxStorageBufferRange;
    const uint64_t slot_bytes = std::max<uint64_t>(kept.instances, 1) * vk::kLidarSplatGradFloats * 4;
    if (slot_bytes > limit) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "vulkan LiDAR: the deterministic backward needs ", slot_bytes, " bytes of slots for ",
          kept.instances, " tile instances, more than the storage buffer range of ", limit,
          " bytes; use the default (atomic) backward"));
    }
    for (auto [buffer, bytes, name] :
         {std::tuple{&det_slots, VkDeviceSize{slot_bytes}, "lidar_det_slots"},
          std::tuple{&det_rank_of, VkDeviceSize{std::max<uint32_t>(n, 1)} * 8, "lidar_det_rank_of"}}) {
      if (absl::Status s = EnsureBufferCapacity(c, buffer, bytes, vk::Buffer::Kind::kDevice, name); !s.ok()) {
        return s;
      }
    }
    det_slot_capacity = slot_bytes / (vk::kLidarSplatGradFloats * 4);
  }
  // dL/d range_sum | alpha | intensity_sum into the staging buffer, zeros for a null pointer.
  auto* staging = static_cast<float*>(ray_grads_staging.mapped());
  for (auto [src, plane] : {std::pair{upstream.d_range_sum, 0}, std::pair{upstream.d_alpha, 1},
                            std::pair{upstream.d_intensity_sum, 2}}) {
    if (src != nullptr) {
      std::memcpy(staging + plane * P, src, P * 4);
    } else {
      std::memset(staging + plane * P, 0, P * 4);
    }
  }
  if (absl::Status s = vk::BeginFrameCommands(cmd, *arena); !s.ok()) return s;
  vk::Recorder rec(c, cmd, arena.get());
  vk::AttachProfiler(rec, profiler.get());
  rec.Copy(ray_grads_staging, 0, ray_grads, 0, VkDeviceSize{P} * 12);
  rec.Barrier();
  const vk::LidarBackwardPush push{kept.blend.columns, kept.blend.beams, kept.blend.tiles_x,
                                   kept.blend.rank_mask, kept.blend.splat_capacity};
  vk::RecordLidarBackward(rec, *kernels, Frame(kept.project.has_refl != 0), kept.bins, kept.project, push,
                          vk::LidarBackwardBuffers{&ray_grads, &splat_grads, &param_grads,
                                                   deterministic ? &det_slots : nullptr,
                                                   det_slot_capacity, &det_rank_of, &counts, &args});
  if (n > 0) rec.Copy(param_grads, 0, bwd_readback, 0, VkDeviceSize{n} * vk::kLidarParamGradFloats * 4);
  if (absl::Status s = vk::SubmitFrameAndWait(c, rec, fence, bwd_readback, profiler.get()); !s.ok()) return s;
  vk::UnpackLidarGrads(static_cast<const float*>(bwd_readback.mapped()), n, grads);
  return absl::OkStatus();
}

absl::Status VulkanLidarRenderer::Backward(const LidarUpstreamGrads& upstream, LidarGaussianGrads* grads,
                                           bool deterministic) {
  return impl_->Backward(upstream, grads, deterministic);
}

absl::Status VulkanLidarRenderer::Render(const LidarModel& model, const LidarSweepPose& sweep,
                                         const LidarRenderOptions& options, LidarRenderOutput* out) {
  return impl_->Render(model, sweep, options, out);
}

absl::Status VulkanLidarRenderer::Render(const LidarModel& model,
                                         const Eigen::Isometry3d& T_world_from_lidar,
                                         const LidarRenderOptions& options, LidarRenderOutput* out) {
  return impl_->Render(model, LidarSweepPose::Static(T_world_from_lidar), options, out);
}

absl::Status VulkanLidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                         const Eigen::Isometry3d& T_world_from_lidar,
                                         const LidarRenderOptions& options, LidarRenderOutput* out) {
  if (absl::Status s = Upload(store); !s.ok()) return s;
  return Render(model, T_world_from_lidar, options, out);
}

absl::Status VulkanLidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                         const LidarSweepPose& sweep, const LidarRenderOptions& options,
                                         LidarRenderOutput* out) {
  if (absl::Status s = Upload(store); !s.ok()) return s;
  return Render(model, sweep, options, out);
}

}  // namespace streetsim
