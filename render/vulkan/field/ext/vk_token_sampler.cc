#include "render/vulkan/field/ext/vk_token_sampler.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "scene/field/extended/extended_sampling.h"
#include "render/vulkan/field/field_device_util.h"
#include "streetsim_spirv.h"

namespace streetsim::field {

namespace vk = vulkan;

namespace {

constexpr uint32_t kWg = 256;                    // field_common.glsl: FIELD_WG
constexpr uint32_t kGaussiansPerBackwardWg = 8;  // ext_sample_backward.glsl: 256 / LANES
constexpr int kBindings = 14;                    // ext_sample_backward.glsl: 0..13

// ext_common.glsl: ExtSamplePush.
struct ExtSamplePush {
  float ax, ay, az, bx, by, bz;
  uint32_t rows, time_res, tokens;
  uint32_t s_base, s_stride, geom_cols;
  uint32_t dilation;
  float token_time[kVkMaxTokens];
};

uint32_t DivUp(uint64_t a, uint64_t b) { return static_cast<uint32_t>((a + b - 1) / b); }

}  // namespace

VkTokenSampler::~VkTokenSampler() = default;

absl::StatusOr<std::unique_ptr<VkTokenSampler>> VkTokenSampler::Create(const vk::Context& ctx,
                                                                      const FieldLayout& layout, int tokens,
                                                                      int dilation, size_t max_plane_buffer_bytes,
                                                                      bool force_cas_atomics) {
  if (tokens < 1 || tokens > kVkMaxTokens) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan extended field: ", tokens, " tokens, the kernels take 1..", kVkMaxTokens));
  }
  const VkPhysicalDeviceLimits& lim = ctx.limits();
  if (lim.maxPerStageDescriptorStorageBuffers < static_cast<uint32_t>(kBindings)) {
    return absl::FailedPreconditionError(absl::StrCat("vulkan extended field: device binds ",
                                                      lim.maxPerStageDescriptorStorageBuffers,
                                                      " storage buffers per stage, the kernels need ", kBindings));
  }
  if (dilation < 0) return absl::InvalidArgumentError("vulkan extended field: negative dilation");
  std::unique_ptr<VkTokenSampler> s(new VkTokenSampler(ctx, layout, tokens, dilation));
  s->float_atomics_ = ctx.has_float_atomic_add() && !force_cas_atomics;
  const size_t range = lim.maxStorageBufferRange;
  const size_t limit = std::min<size_t>(max_plane_buffer_bytes > 0 ? max_plane_buffer_bytes : range, range);
  absl::StatusOr<PlaneGroups> groups = PackPlaneGroups(layout, limit);
  if (!groups.ok()) return groups.status();
  s->groups_ = *std::move(groups);
  for (size_t g = 0; g < s->groups_.begin.size(); ++g) {
    const size_t bytes = (s->groups_.end[g] - s->groups_.begin[g]) * sizeof(float);
    for (auto [list, name] : {std::pair{&s->planes_, "ext planes "}, std::pair{&s->grads_, "ext plane grads "}}) {
      auto b = vk::Buffer::Create(ctx, bytes, vk::Buffer::Kind::kDevice, absl::StrCat(name, g));
      if (!b.ok()) return b.status();
      list->push_back(*std::move(b));
    }
  }
  const std::vector<uint32_t>& table = s->groups_.table;
  auto t = vk::Buffer::Create(ctx, table.size() * 4, vk::Buffer::Kind::kDevice, "ext plane table");
  if (!t.ok()) return t.status();
  s->table_ = *std::move(t);
  if (auto st = vk::UploadBytes(ctx, s->table_, table.data(), table.size() * 4); !st.ok()) return st;
  // field_planes.glsl: CHANNELS, LEVELS.
  const vk::SpecConstant sizes[] = {{0, static_cast<uint32_t>(layout.channels)},
                                    {1, static_cast<uint32_t>(layout.num_levels)}};
  const vk::PipelineSpec specs[] = {
      {&s->forward_, "ext_sample", spirv::ext_sample, 10, sizeof(ExtSamplePush), sizes},
      {&s->backward_, "ext_sample_backward",
       s->float_atomics_ ? spirv::ext_sample_backward : spirv::ext_sample_backward_cas, kBindings,
       sizeof(ExtSamplePush), sizes},
  };
  if (auto st = vk::CreatePipelines(ctx, specs); !st.ok()) return st;
  return s;
}

absl::Status VkTokenSampler::UploadPlanes(std::span<const float> params) {
  if (params.size() != layout_.total) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan extended field: ", params.size(), " base parameters, the layout has ", layout_.total));
  }
  for (size_t g = 0; g < planes_.size(); ++g) {
    if (auto s = vk::UploadBytes(ctx_, planes_[g], params.data() + groups_.begin[g],
                                 (groups_.end[g] - groups_.begin[g]) * sizeof(float));
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

void VkTokenSampler::SetPass(const FieldAabb& aabb, double time_coord, double dt) {
  // TokenSampler's own normaliser and token times (double, rounded once): the same floats as the cpu.
  const internal::TokenSampler<float> cpu(layout_, nullptr, aabb, time_coord, K_, dt);
  std::copy(cpu.nm_a, cpu.nm_a + 3, nm_a_);
  std::copy(cpu.nm_b, cpu.nm_b + 3, nm_b_);
  std::copy(cpu.token_time.begin(), cpu.token_time.end(), token_time_);
}

void VkTokenSampler::RecordForward(vk::Recorder& rec, uint32_t rows, const vk::Buffer& means, const SView& s,
                                   const vk::Buffer& ftok, const vk::Buffer* s_dil) const {
  const bool dil = dilation_ > 0 && s_dil != nullptr;
  ExtSamplePush p{nm_a_[0], nm_a_[1], nm_a_[2], nm_b_[0], nm_b_[1], nm_b_[2], rows,
                  static_cast<uint32_t>(layout_.time_resolution), static_cast<uint32_t>(K_),
                  s.base, s.buffer ? s.stride : 0u, s.geom ? s.geom_cols : 0u,
                  dil ? static_cast<uint32_t>(dilation_) : 0u, {}};
  std::copy(token_time_, token_time_ + kVkMaxTokens, p.token_time);
  // Absent outputs / inputs bind a stand-in (never accessed: stride 0, geom_cols 0).
  rec.Dispatch(*forward_,
               {PlaneBuf(0), PlaneBuf(1), PlaneBuf(2), PlaneBuf(3), &table_, &means, s.buffer ? s.buffer : &ftok,
                &ftok, s.geom ? s.geom : &means, dil ? s_dil : &ftok},
               p, vk::GridFor(DivUp(uint64_t{rows} * layout_.feature_dim(), kWg)));
}

void VkTokenSampler::RecordBackward(vk::Recorder& rec, uint32_t rows, const vk::Buffer& means, const SView& d_s,
                                    const vk::Buffer& d_ftok, const vk::Buffer* d_sdil,
                                    const vk::Buffer& d_means) const {
  const bool dil = dilation_ > 0 && d_sdil != nullptr;
  ExtSamplePush p{nm_a_[0], nm_a_[1], nm_a_[2], nm_b_[0], nm_b_[1], nm_b_[2], rows,
                  static_cast<uint32_t>(layout_.time_resolution), static_cast<uint32_t>(K_),
                  d_s.base, d_s.buffer ? d_s.stride : 0u, 0u, dil ? static_cast<uint32_t>(dilation_) : 0u, {}};
  std::copy(token_time_, token_time_ + kVkMaxTokens, p.token_time);
  rec.Dispatch(*backward_,
               {PlaneBuf(0), PlaneBuf(1), PlaneBuf(2), PlaneBuf(3), &table_, &means, &d_ftok, &d_means, GradBuf(0),
                GradBuf(1), GradBuf(2), GradBuf(3), d_s.buffer ? d_s.buffer : &d_ftok, dil ? d_sdil : &d_ftok},
               p, vk::GridFor(DivUp(rows, kGaussiansPerBackwardWg)));
}

void VkTokenSampler::RecordZeroGrads(vk::Recorder& rec) const {
  for (const vk::Buffer& g : grads_) rec.Fill(g, 0, VK_WHOLE_SIZE, 0);
}

absl::Status VkTokenSampler::DownloadAddGrads(vk::Buffer* readback, float* d_base) const {
  for (size_t g = 0; g < grads_.size(); ++g) {
    if (auto s = DownloadAdd(ctx_, grads_[g], groups_.end[g] - groups_.begin[g], readback, d_base + groups_.begin[g]);
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

}  // namespace streetsim::field
