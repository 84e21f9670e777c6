// VulkanField's optimiser on the device: the plane regularisers' gradient and Adam over the
// parameters where they live (docs/field.md "The optimiser on the device"). Same
// formulas as the cpu's PlaneRegularizers and FieldAdamStep; tests/field/vulkan_field_optimizer_test.cc
// holds them against each other.
#include <algorithm>
#include <cstring>
#include <tuple>
#include <type_traits>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/vulkan/field/vulkan_field_impl.h"
#include "scene/optim/adam_kernel.h"
#include "streetsim_spirv.h"

namespace streetsim::field {

namespace {

// field_plane_reg.comp's push constants.
struct PlaneRegPush {
  uint32_t offset, row_len, height, groups;
  float c_s2, c_l1, inv_n_s2, inv_n_l1;
  uint32_t partial_off;
};
// field_adam.comp's.
struct AdamPush {
  uint32_t count;
  float step_size, inv_sqrt_bc2;
  float beta1 = optim::kAdamBeta1, one_minus_beta1 = 1 - optim::kAdamBeta1;
  float beta2 = optim::kAdamBeta2, one_minus_beta2 = 1 - optim::kAdamBeta2;
  float eps = optim::kAdamEps;
};

// Workgroups per plane for the regularisers (a grid-stride loop beyond): enough to fill a GPU,
// few enough that the per-workgroup loss sums stay a small read-back.
constexpr uint32_t kMaxRegGroupsPerPlane = 2048;

// Where plane `p` lives: its group and its offset in that group.
struct PlaneSlot {
  int group = 0;
  size_t offset = 0;
};
PlaneSlot SlotOf(const VulkanField::Impl& m, const PlaneInfo& p) {
  for (size_t g = 0; g < m.group_begin.size(); ++g) {
    if (p.offset >= m.group_begin[g] && p.offset < m.group_end[g]) {
      return PlaneSlot{static_cast<int>(g), p.offset - m.group_begin[g]};
    }
  }
  return PlaneSlot{};  // unreachable: PackPlaneGroups covers every plane
}

uint32_t RegGroups(const PlaneInfo& p, int channels) {
  return std::clamp<uint32_t>(DivUp(p.size(channels), kWg), 1, kMaxRegGroupsPerPlane);
}

}  // namespace

absl::Status VulkanField::Impl::ZeroGradients() {
  return ctx->SubmitAndWait([&](VkCommandBuffer cmd) {
    for (const vk::Buffer& g : grads) vkCmdFillBuffer(cmd, g.handle(), 0, VK_WHOLE_SIZE, 0);
    vkCmdFillBuffer(cmd, d_mlp.handle(), 0, VK_WHOLE_SIZE, 0);
  });
}

absl::Status VulkanField::Impl::EnsureOptimizer() {
  if (adam) return absl::OkStatus();
  absl::Status s = MakeOptimizer();
  if (!s.ok()) {  // nothing half-made stays: a later call tries again, or the host optimiser runs
    plane_reg.reset();
    adam.reset();
    m_planes.clear();
    v_planes.clear();
    m_mlp = vk::Buffer();
    v_mlp = vk::Buffer();
    reg_partials = vk::Buffer();
    reg_readback = vk::Buffer();
  }
  return s;
}

absl::Status VulkanField::Impl::MakeOptimizer() {
  const vk::Context& c = *ctx;
  const vk::PipelineSpec specs[] = {
      {&plane_reg, "field_plane_reg", spirv::field_plane_reg, 3, sizeof(PlaneRegPush), {}},
      {&adam, "field_adam", spirv::field_adam, 4, sizeof(AdamPush), {}},
  };
  if (auto s = vk::CreatePipelines(c, specs); !s.ok()) return s;
  if (auto s = MakeGroupBuffers(&m_planes, "field adam m"); !s.ok()) return s;
  if (auto s = MakeGroupBuffers(&v_planes, "field adam v"); !s.ok()) return s;
  uint32_t slots = 0;
  for (const PlaneInfo& p : layout.planes) slots += RegGroups(p, layout.channels);
  for (auto [buf, bytes, name] : {std::tuple{&m_mlp, mlp_total * 4, "field adam m mlp"},
                                  std::tuple{&v_mlp, mlp_total * 4, "field adam v mlp"},
                                  std::tuple{&reg_partials, size_t{slots} * 8, "field reg partials"}}) {
    if (auto s = MakeBuffer(c, buf, bytes, vk::Buffer::Kind::kDevice, name); !s.ok()) return s;
  }
  if (auto s = MakeBuffer(c, &reg_readback, size_t{slots} * 8, vk::Buffer::Kind::kReadback, "field reg readback");
      !s.ok()) {
    return s;
  }
  // Moments start at zero (a fresh Adam) until SetAdamMoments says otherwise.
  return ctx->SubmitAndWait([&](VkCommandBuffer cmd) {
    for (const std::vector<vk::Buffer>* set : {&m_planes, &v_planes}) {
      for (const vk::Buffer& b : *set) vkCmdFillBuffer(cmd, b.handle(), 0, VK_WHOLE_SIZE, 0);
    }
    vkCmdFillBuffer(cmd, m_mlp.handle(), 0, VK_WHOLE_SIZE, 0);
    vkCmdFillBuffer(cmd, v_mlp.handle(), 0, VK_WHOLE_SIZE, 0);
  });
}

absl::Status VulkanField::PrepareOptimizer() { return impl_->EnsureOptimizer(); }

absl::StatusOr<RegularizerLosses> VulkanField::RegularizeAndStep(const RegularizerWeights& w, const FieldLrs& lrs,
                                                                 int64_t step) {
  Impl& m = *impl_;
  if (step < 1) return absl::InvalidArgumentError(absl::StrCat("vulkan field: Adam step ", step, ", want >= 1"));
  if (auto s = m.EnsureOptimizer(); !s.ok()) return s;
  const FieldLayout& L = m.layout;

  vk::Recorder rec(*m.ctx, m.frame.cmd, m.frame.arena.get());
  if (auto s = m.frame.Begin(rec); !s.ok()) return s;
  // Regularisers first: their gradient is taken at the parameters before the step (the cpu's order).
  std::vector<bool> time_plane_of_slot;
  uint32_t slot = 0;
  for (const PlaneInfo& p : L.planes) {
    const bool time_plane = PlaneHasTime(p.plane);
    const double w_s2 = time_plane ? w.time_smoothness : w.plane_tv;
    const double w_l1 = time_plane ? w.l1_time_planes : 0;
    const size_t row_len = static_cast<size_t>(p.width) * L.channels;
    const double n_s2 = static_cast<double>(p.height - 2) * row_len;
    const double n_l1 = static_cast<double>(p.height) * row_len;
    const PlaneSlot where = SlotOf(m, p);
    const uint32_t groups = RegGroups(p, L.channels);
    const PlaneRegPush push{static_cast<uint32_t>(where.offset),
                            static_cast<uint32_t>(row_len),
                            static_cast<uint32_t>(p.height),
                            groups,
                            p.height >= 3 ? static_cast<float>(2 * w_s2 / n_s2) : 0.0f,
                            static_cast<float>(w_l1 / n_l1),
                            p.height >= 3 ? static_cast<float>(1 / n_s2) : 0.0f,
                            time_plane ? static_cast<float>(1 / n_l1) : 0.0f,
                            slot};
    rec.Dispatch(*m.plane_reg, {m.PlaneBuf(where.group), m.GradBuf(where.group), &m.reg_partials}, push,
                 vk::GridFor(groups));
    time_plane_of_slot.insert(time_plane_of_slot.end(), groups, time_plane);
    slot += groups;
  }
  rec.Barrier();

  // Adam: the planes at the grid rate, the MLP at the deformation rate (FieldAdamStep's groups).
  const FieldAdamScales scales = FieldAdamStepScales(lrs, step);
  for (size_t g = 0; g < m.planes.size(); ++g) {
    const AdamPush push{static_cast<uint32_t>(m.group_end[g] - m.group_begin[g]), scales.grid_step,
                        scales.inv_sqrt_bc2};
    rec.Dispatch(*m.adam, {&m.planes[g], &m.grads[g], &m.m_planes[g], &m.v_planes[g]}, push,
                 vk::GridFor(DivUp(push.count, kWg)));
  }
  const AdamPush mlp_push{static_cast<uint32_t>(m.mlp_total), scales.mlp_step, scales.inv_sqrt_bc2};
  rec.Dispatch(*m.adam, {&m.mlp, &m.d_mlp, &m.m_mlp, &m.v_mlp}, mlp_push, vk::GridFor(DivUp(m.mlp_total, kWg)));
  rec.Barrier();
  rec.Copy(m.reg_partials, 0, m.reg_readback, 0, size_t{slot} * 8);
  if (auto s = m.frame.SubmitAndWait(rec, m.reg_readback); !s.ok()) return s;

  RegularizerLosses out;
  const float* sums = static_cast<const float*>(m.reg_readback.mapped());
  for (uint32_t k = 0; k < slot; ++k) {
    (time_plane_of_slot[k] ? out.time_smoothness : out.spatial_smoothness) += sums[2 * k];
    out.l1_time += sums[2 * k + 1];
  }
  out.weighted = w.plane_tv * out.spatial_smoothness + w.time_smoothness * out.time_smoothness +
                 w.l1_time_planes * out.l1_time;
  return out;
}

namespace {

// Copies between a host array in FieldLayout order and the device's per-group buffers.
template <typename Fn>
absl::Status ForEachGroup(const VulkanField::Impl& m, const std::vector<vk::Buffer>& plane_bufs,
                          const vk::Buffer& mlp_buf, Fn fn) {
  for (size_t g = 0; g < plane_bufs.size(); ++g) {
    if (auto s = fn(plane_bufs[g], m.group_begin[g], m.group_end[g] - m.group_begin[g]); !s.ok()) return s;
  }
  return fn(mlp_buf, m.layout.grid_size, m.mlp_total);
}

absl::Status CheckSize(std::span<const float> a, size_t total, const char* what) {
  if (a.size() == total) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat("vulkan field: ", what, " has ", a.size(), " floats, the layout ",
                                                 total));
}

}  // namespace

namespace {

// Adam's moments between host arrays (FieldLayout order) and the device: uploaded from const
// arrays, downloaded into writable ones.
template <typename T>
absl::Status TransferMoments(VulkanField::Impl& m, T* m_host, T* v_host) {
  if (auto s = m.EnsureOptimizer(); !s.ok()) return s;
  for (auto [host, bufs, mlp] : {std::tuple{m_host, &m.m_planes, &m.m_mlp}, std::tuple{v_host, &m.v_planes, &m.v_mlp}}) {
    if (auto s = ForEachGroup(m, *bufs, *mlp,
                              [&](const vk::Buffer& b, size_t begin, size_t count) {
                                if constexpr (std::is_const_v<T>) {
                                  return vk::UploadBytes(*m.ctx, b, host + begin, count * sizeof(float));
                                } else {
                                  return vk::DownloadBytes(*m.ctx, b, host + begin, count * sizeof(float));
                                }
                              });
        !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status VulkanField::SetAdamMoments(std::span<const float> m_in, std::span<const float> v_in) {
  if (auto s = CheckSize(m_in, impl_->layout.total, "Adam's m"); !s.ok()) return s;
  if (auto s = CheckSize(v_in, impl_->layout.total, "Adam's v"); !s.ok()) return s;
  return TransferMoments(*impl_, m_in.data(), v_in.data());
}

absl::Status VulkanField::ReadAdamMoments(std::span<float> m_out, std::span<float> v_out) {
  if (auto s = CheckSize(m_out, impl_->layout.total, "Adam's m"); !s.ok()) return s;
  if (auto s = CheckSize(v_out, impl_->layout.total, "Adam's v"); !s.ok()) return s;
  return TransferMoments(*impl_, m_out.data(), v_out.data());
}

absl::Status VulkanField::ReadParams(std::span<float> params) {
  Impl& m = *impl_;
  if (auto s = CheckSize(params, m.layout.total, "the parameter array"); !s.ok()) return s;
  return ForEachGroup(m, m.planes, m.mlp, [&](const vk::Buffer& b, size_t begin, size_t count) {
    return vk::DownloadBytes(*m.ctx, b, params.data() + begin, count * sizeof(float));
  });
}

}  // namespace streetsim::field
