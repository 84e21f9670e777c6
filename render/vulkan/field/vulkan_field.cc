// VulkanField: buffers, the plane groups, per-batch command recording (kernels in shaders/,
// docs/field.md "Vulkan field").
#include "render/vulkan/field/vulkan_field.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/field/field_linear_push.h"
#include "render/vulkan/field/field_device_util.h"
#include "render/vulkan/field/plane_groups.h"
#include "render/vulkan/field/vulkan_field_impl.h"
#include "streetsim_spirv.h"

namespace streetsim::field {

namespace vk = vulkan;

absl::Status VulkanField::Impl::Init(std::span<const float> params) {
  const vk::Context& c = *ctx;
  const VkPhysicalDeviceLimits& lim = c.limits();
  if (lim.maxPerStageDescriptorStorageBuffers < static_cast<uint32_t>(kMaxBindings)) {
    return absl::FailedPreconditionError(absl::StrCat("vulkan field: device binds ",
                                                      lim.maxPerStageDescriptorStorageBuffers,
                                                      " storage buffers per stage, the kernels need ", kMaxBindings));
  }
  float_atomics = c.has_float_atomic_add() && !options.force_cas_atomics;
  const size_t range = lim.maxStorageBufferRange;
  const size_t group_limit =
      std::min<size_t>(options.max_plane_buffer_bytes > 0 ? options.max_plane_buffer_bytes : range, range);
  absl::StatusOr<PlaneGroups> packed = PackPlaneGroups(layout, group_limit);
  if (!packed.ok()) return packed.status();
  group_begin = packed->begin;
  group_end = packed->end;
  const std::vector<uint32_t>& table = packed->table;
  if (auto s = MakeGroupBuffers(&planes, "field planes"); !s.ok()) return s;
  if (auto s = MakeGroupBuffers(&grads, "field grads"); !s.ok()) return s;
  mlp_total = layout.total - layout.grid_size;
  if (auto s = MakeBuffer(c, &plane_table, table.size() * 4, vk::Buffer::Kind::kDevice, "field plane table");
      !s.ok()) {
    return s;
  }
  if (auto s = vk::UploadBytes(c, plane_table, table.data(), table.size() * 4); !s.ok()) return s;
  if (auto s = MakeBuffer(c, &mlp, mlp_total * 4, vk::Buffer::Kind::kDevice, "field mlp"); !s.ok()) return s;
  if (auto s = MakeBuffer(c, &d_mlp, mlp_total * 4, vk::Buffer::Kind::kDevice, "field d_mlp"); !s.ok()) return s;

  // Batch size: every per-row buffer within the buffer range, every index within 32 bits.
  const size_t D = layout.feature_dim();
  const size_t widest = std::max<size_t>({D, static_cast<size_t>(layout.width), kShOutputs});
  batch = std::min<size_t>({std::max<size_t>(options.batch_rows, 1), range / (widest * 4), (size_t{1} << 31) / widest});
  if (batch < 1) return absl::FailedPreconditionError("vulkan field: a single row exceeds the buffer range");
  const size_t max_chunks = range / (mlp_total * 4);
  if (max_chunks < 1) return absl::FailedPreconditionError("vulkan field: the MLP exceeds the buffer range");
  rows_per_chunk = std::max(kMinRowsPerChunk, (batch + max_chunks - 1) / max_chunks);
  chunks = (batch + rows_per_chunk - 1) / rows_per_chunk;

  const size_t B = batch;
  const size_t W = layout.width;
  struct Row {
    vk::Buffer* b;
    size_t floats;
    const char* name;
    vk::Buffer::Kind kind = vk::Buffer::Kind::kDevice;
  };
  for (const Row& r : {Row{&means, B * 3, "field means"}, Row{&features, B * D, "field features"},
                       Row{&act, B * W, "field trunk"}, Row{&pos_hidden, B * W, "field pos hidden"},
                       Row{&sh_hidden, B * W, "field sh hidden"}, Row{&dx, B * 3, "field dx"},
                       Row{&dsh, B * kShOutputs, "field dsh"},
                       Row{&staging, B * (6 + kShOutputs), "field staging", vk::Buffer::Kind::kStaging},
                       Row{&readback, B * (6 + kShOutputs), "field readback", vk::Buffer::Kind::kReadback}}) {
    if (auto s = MakeBuffer(c, r.b, r.floats * 4, r.kind, r.name); !s.ok()) return s;
  }

  // field_planes.glsl: CHANNELS, LEVELS.
  const vk::SpecConstant sizes[] = {{0, static_cast<uint32_t>(layout.channels)},
                                    {1, static_cast<uint32_t>(layout.num_levels)}};
  const vk::PipelineSpec specs[] = {
      {&sample, "field_sample", spirv::field_sample, 7, sizeof(SamplePush), sizes},
      {&linear, "field_linear", spirv::field_linear, 4, sizeof(LinearPush), {}},
      {&linear_grad, "field_linear_grad", spirv::field_linear_grad, 3, sizeof(GradPush), {}},
      {&reduce, "field_reduce", spirv::field_reduce, 2, sizeof(ReducePush), {}},
      {&sample_backward, "field_sample_backward",
       float_atomics ? spirv::field_sample_backward : spirv::field_sample_backward_cas, kMaxBindings,
       sizeof(SamplePush), sizes},
  };
  if (auto s = vk::CreatePipelines(c, specs); !s.ok()) return s;
  if (auto s = frame.Create(c); !s.ok()) return s;
  return Upload(params);
}

absl::Status VulkanField::Impl::Upload(std::span<const float> params) {
  if (params.size() != layout.total) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan field: ", params.size(), " parameters, the layout has ", layout.total));
  }
  for (size_t g = 0; g < planes.size(); ++g) {
    if (auto s = vk::UploadBytes(*ctx, planes[g], params.data() + group_begin[g],
                                 (group_end[g] - group_begin[g]) * sizeof(float));
        !s.ok()) {
      return s;
    }
  }
  return vk::UploadBytes(*ctx, mlp, params.data() + layout.grid_size, mlp_total * sizeof(float));
}

absl::Status VulkanField::Impl::EnsureBackwardBuffers() {
  if (partials.valid()) return absl::OkStatus();
  const size_t B = batch, W = layout.width, D = layout.feature_dim();
  struct Row {
    vk::Buffer* b;
    size_t floats;
    const char* name;
  };
  for (const Row& r : {Row{&g_dx, B * 3, "field g_dx"}, Row{&g_dsh, B * kShOutputs, "field g_dsh"},
                       Row{&d_pos_hidden, B * W, "field d_pos_hidden"}, Row{&d_sh_hidden, B * W, "field d_sh_hidden"},
                       Row{&d_act, B * W, "field d_act"}, Row{&d_features, B * D, "field d_features"},
                       Row{&d_means, B * 3, "field d_means"}, Row{&partials, chunks * mlp_total, "field partials"}}) {
    if (auto s = MakeBuffer(*ctx, r.b, r.floats * 4, vk::Buffer::Kind::kDevice, r.name); !s.ok()) return s;
  }
  size_t largest = mlp_total;
  for (size_t g = 0; g < planes.size(); ++g) largest = std::max(largest, group_end[g] - group_begin[g]);
  return MakeBuffer(*ctx, &grad_readback, largest * 4, vk::Buffer::Kind::kReadback, "field grad readback");
}

SamplePush VulkanField::Impl::MakeSamplePush(const FieldQuery& q, size_t rows) const {
  // As field_eval.cc's Normaliser: p = a x + b, computed in double, rounded once.
  float a[3], b[3];
  for (int k = 0; k < 3; ++k) {
    const double ext = q.aabb_max[k] - q.aabb_min[k];
    a[k] = static_cast<float>(-2.0 / ext);
    b[k] = static_cast<float>(1.0 + 2.0 * q.aabb_min[k] / ext);
  }
  return SamplePush{a[0], a[1], a[2], b[0], b[1], b[2], static_cast<float>(q.time_coord),
                    static_cast<uint32_t>(rows), static_cast<uint32_t>(layout.time_resolution)};
}

namespace {

absl::Status CheckQuery(const FieldQuery& q) {
  for (int k = 0; k < 3; ++k) {
    const double ext = q.aabb_max[k] - q.aabb_min[k];
    if (!std::isfinite(q.aabb_min[k]) || !std::isfinite(q.aabb_max[k]) || !(ext > 0)) {
      return absl::InvalidArgumentError("vulkan field: the query's AABB needs a finite positive extent per axis");
    }
  }
  return absl::OkStatus();
}

}  // namespace

VulkanField::VulkanField(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
VulkanField::~VulkanField() = default;

absl::StatusOr<std::unique_ptr<VulkanField>> VulkanField::Create(const FieldLayout& layout,
                                                                 std::span<const float> params,
                                                                 const VulkanFieldOptions& options) {
  if (auto s = CheckLayout(layout); !s.ok()) return s;
  if (params.size() != layout.total) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan field: ", params.size(), " parameters, the layout has ", layout.total));
  }
  auto impl = std::make_unique<Impl>();
  auto ctx = vk::Context::Create(options.device);
  if (!ctx.ok()) return ctx.status();
  impl->ctx = *std::move(ctx);
  impl->layout = layout;
  impl->options = options;
  if (auto s = impl->Init(params); !s.ok()) return s;
  return std::unique_ptr<VulkanField>(new VulkanField(std::move(impl)));
}

absl::StatusOr<std::unique_ptr<VulkanField>> VulkanField::Create(const DeformationField& field,
                                                                 const VulkanFieldOptions& options) {
  return Create(field.layout(), field.params(), options);
}

absl::Status VulkanField::UpdateParams(std::span<const float> params) { return impl_->Upload(params); }

absl::Status VulkanField::Forward(const FieldQuery& query, std::span<const float> means_in, std::vector<float>* dx_out,
                                  std::vector<float>* dsh_out) {
  Impl& m = *impl_;
  const auto t0 = std::chrono::steady_clock::now();
  if (dx_out == nullptr) return absl::InvalidArgumentError("vulkan field: Forward needs dx");
  if (means_in.size() % 3 != 0) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan field: ", means_in.size(), " mean floats, not n * 3"));
  }
  if (auto s = CheckQuery(query); !s.ok()) return s;
  const size_t n = means_in.size() / 3;
  dx_out->resize(n * 3);
  if (dsh_out) dsh_out->resize(n * kShOutputs);
  const FieldLayout& L = m.layout;
  const uint32_t W = L.width;
  VulkanFieldTimings timings;
  for (size_t b0 = 0; b0 < n; b0 += m.batch) {
    const size_t bn = std::min(m.batch, n - b0);
    const uint32_t rows = static_cast<uint32_t>(bn);
    std::memcpy(m.staging.mapped(), means_in.data() + b0 * 3, bn * 3 * sizeof(float));
    vk::Recorder rec(*m.ctx, m.frame.cmd, m.frame.arena.get());
    if (auto s = m.frame.Begin(rec); !s.ok()) return s;
    rec.Copy(m.staging, 0, m.means, 0, bn * 3 * sizeof(float));
    rec.Barrier();
    m.frame.WriteTimestamp(0);
    m.RecordHidden(rec, query, bn, true, dsh_out != nullptr);
    rec.Barrier();
    m.Linear(rec, m.pos_hidden, m.dx, nullptr, rows, W, 3, L.pos2, kBias);
    if (dsh_out) m.Linear(rec, m.sh_hidden, m.dsh, nullptr, rows, W, kShOutputs, L.sh2, kBias);
    rec.Barrier();
    m.frame.WriteTimestamp(1);
    rec.Copy(m.dx, 0, m.readback, 0, bn * 3 * sizeof(float));
    if (dsh_out) rec.Copy(m.dsh, 0, m.readback, m.batch * 3 * sizeof(float), bn * kShOutputs * sizeof(float));
    if (auto s = m.frame.SubmitAndWait(rec, m.readback); !s.ok()) return s;
    const float* out = static_cast<const float*>(m.readback.mapped());
    std::memcpy(dx_out->data() + b0 * 3, out, bn * 3 * sizeof(float));
    if (dsh_out) {
      std::memcpy(dsh_out->data() + b0 * kShOutputs, out + m.batch * 3, bn * kShOutputs * sizeof(float));
    }
    timings.device_ms += m.frame.ReadTimestampsMs();
    ++timings.batches;
  }
  timings.wall_ms = MsSince(t0);
  m.last_forward = timings;
  return absl::OkStatus();
}

absl::Status VulkanField::Backward(const FieldQuery& query, std::span<const float> means_in,
                                   std::span<const float> d_dx, std::span<const float> d_dsh,
                                   std::span<float> d_params, std::span<float> d_means_out) {
  if (d_params.size() != impl_->layout.total) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan field: d_params has ", d_params.size(), " floats, the layout ", impl_->layout.total));
  }
  return impl_->Backward(query, means_in, d_dx, d_dsh, d_params, d_means_out);
}

absl::Status VulkanField::BackwardOnDevice(const FieldQuery& query, std::span<const float> means,
                                           std::span<const float> d_dx, std::span<const float> d_dsh,
                                           std::span<float> d_means) {
  return impl_->Backward(query, means, d_dx, d_dsh, {}, d_means);
}

absl::Status VulkanField::Impl::Backward(const FieldQuery& query, std::span<const float> means_in,
                                         std::span<const float> d_dx, std::span<const float> d_dsh,
                                         std::span<float> d_params, std::span<float> d_means_out) {
  Impl& m = *this;
  const bool download = !d_params.empty();
  const auto t0 = std::chrono::steady_clock::now();
  const FieldLayout& L = m.layout;
  if (means_in.size() % 3 != 0) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan field: ", means_in.size(), " mean floats, not n * 3"));
  }
  const size_t n = means_in.size() / 3;
  if (!d_dx.empty() && d_dx.size() != n * 3) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan field: dL/ddx has ", d_dx.size(), " floats, want ", n * 3));
  }
  if (!d_dsh.empty() && d_dsh.size() != n * kShOutputs) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan field: dL/ddsh has ", d_dsh.size(), " floats, want ", n * kShOutputs));
  }
  if (!d_means_out.empty() && d_means_out.size() != n * 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan field: d_means has ", d_means_out.size(), " floats, want ", n * 3));
  }
  if (auto s = CheckQuery(query); !s.ok()) return s;
  VulkanFieldTimings timings;
  const bool has_dx = !d_dx.empty(), has_dsh = !d_dsh.empty();
  if (n == 0 || (!has_dx && !has_dsh)) {  // every gradient is 0 (as the cpu: dL/dF = 0)
    // The device optimiser steps on the device gradient: it must read 0, not the last call's.
    if (!download) {
      if (auto s = ZeroGradients(); !s.ok()) return s;
    }
    timings.wall_ms = MsSince(t0);
    m.last_backward = timings;
    return absl::OkStatus();
  }
  if (auto s = m.EnsureBackwardBuffers(); !s.ok()) return s;
  const uint32_t D = L.feature_dim(), W = L.width;
  const size_t B = m.batch;
  for (size_t b0 = 0; b0 < n; b0 += B) {
    const size_t bn = std::min(B, n - b0);
    const uint32_t rows = static_cast<uint32_t>(bn);
    float* in = static_cast<float*>(m.staging.mapped());
    std::memcpy(in, means_in.data() + b0 * 3, bn * 3 * sizeof(float));
    if (has_dx) std::memcpy(in + B * 3, d_dx.data() + b0 * 3, bn * 3 * sizeof(float));
    if (has_dsh) std::memcpy(in + B * 6, d_dsh.data() + b0 * kShOutputs, bn * kShOutputs * sizeof(float));
    vk::Recorder rec(*m.ctx, m.frame.cmd, m.frame.arena.get());
    if (auto s = m.frame.Begin(rec); !s.ok()) return s;
    if (b0 == 0) {
      for (const vk::Buffer& g : m.grads) rec.Fill(g, 0, VK_WHOLE_SIZE, 0);
      rec.Fill(m.d_mlp, 0, VK_WHOLE_SIZE, 0);
    }
    // A head without output gradient writes no partial sums: its entries must read 0.
    if (!has_dx || !has_dsh) rec.Fill(m.partials, 0, VK_WHOLE_SIZE, 0);
    rec.Copy(m.staging, 0, m.means, 0, bn * 3 * sizeof(float));
    if (has_dx) rec.Copy(m.staging, B * 3 * sizeof(float), m.g_dx, 0, bn * 3 * sizeof(float));
    if (has_dsh) rec.Copy(m.staging, B * 6 * sizeof(float), m.g_dsh, 0, bn * kShOutputs * sizeof(float));
    rec.Barrier();
    m.frame.WriteTimestamp(0);
    // The forward again (the activations are not kept between calls).
    m.RecordHidden(rec, query, bn, has_dx, has_dsh);
    rec.Barrier();
    // Heads: second layers' gradients, then dL/d(hidden) masked by the ReLU.
    if (has_dx) {
      m.LinearGrad(rec, m.g_dx, m.pos_hidden, rows, L.pos2);
      m.Linear(rec, m.g_dx, m.d_pos_hidden, &m.pos_hidden, rows, 3, W, L.pos2, kTrans | kMask);
    }
    if (has_dsh) {
      m.LinearGrad(rec, m.g_dsh, m.sh_hidden, rows, L.sh2);
      m.Linear(rec, m.g_dsh, m.d_sh_hidden, &m.sh_hidden, rows, kShOutputs, W, L.sh2, kTrans | kMask);
    }
    rec.Barrier();
    // First layers of the heads; dL/d(trunk) = (dP W1 + dS V1) * [trunk > 0].
    if (has_dx) {
      m.LinearGrad(rec, m.d_pos_hidden, m.act, rows, L.pos1);
      m.Linear(rec, m.d_pos_hidden, m.d_act, &m.act, rows, W, W, L.pos1, kTrans | (has_dsh ? 0 : kMask));
    }
    if (has_dsh) {
      m.LinearGrad(rec, m.d_sh_hidden, m.act, rows, L.sh1);
      if (has_dx) rec.Barrier();  // the add below reads d_act
      m.Linear(rec, m.d_sh_hidden, m.d_act, &m.act, rows, W, W, L.sh1, kTrans | kMask | (has_dx ? kAccum : 0));
    }
    rec.Barrier();
    m.LinearGrad(rec, m.d_act, m.features, rows, L.trunk);
    m.Linear(rec, m.d_act, m.d_features, nullptr, rows, W, D, L.trunk, kTrans);
    rec.Barrier();
    const SamplePush sp = m.MakeSamplePush(query, bn);
    rec.Dispatch(*m.sample_backward,
                 {m.PlaneBuf(0), m.PlaneBuf(1), m.PlaneBuf(2), m.PlaneBuf(3), &m.plane_table, &m.means,
                  &m.d_features, &m.d_means, m.GradBuf(0), m.GradBuf(1), m.GradBuf(2), m.GradBuf(3)},
                 sp, vk::GridFor(DivUp(bn, kGaussiansPerBackwardWg)));
    const ReducePush rp{static_cast<uint32_t>(m.mlp_total), DivUp(bn, m.rows_per_chunk), 0,
                        static_cast<uint32_t>(m.mlp_total), 0};
    rec.Dispatch(*m.reduce, {&m.partials, &m.d_mlp}, rp, vk::GridFor(DivUp(m.mlp_total, kWg)));
    rec.Barrier();
    m.frame.WriteTimestamp(1);
    if (!d_means_out.empty()) rec.Copy(m.d_means, 0, m.readback, 0, bn * 3 * sizeof(float));
    if (auto s = m.frame.SubmitAndWait(rec, m.readback); !s.ok()) return s;
    if (!d_means_out.empty()) {
      const float* out = static_cast<const float*>(m.readback.mapped());
      float* dm = d_means_out.data() + b0 * 3;
      for (size_t i = 0; i < bn * 3; ++i) dm[i] += out[i];
    }
    timings.device_ms += m.frame.ReadTimestampsMs();
    ++timings.batches;
  }
  if (!download) {  // BackwardOnDevice: the gradient stays for RegularizeAndStep
    timings.wall_ms = MsSince(t0);
    m.last_backward = timings;
    return absl::OkStatus();
  }
  // The gradients, one buffer at a time, added into the caller's array.
  auto download_add = [&](const vk::Buffer& src, size_t floats, float* dst) {
    return DownloadAdd(*m.ctx, src, floats, &m.grad_readback, dst);
  };
  for (size_t g = 0; g < m.grads.size(); ++g) {
    if (auto s = download_add(m.grads[g], m.group_end[g] - m.group_begin[g], d_params.data() + m.group_begin[g]);
        !s.ok()) {
      return s;
    }
  }
  if (auto s = download_add(m.d_mlp, m.mlp_total, d_params.data() + L.grid_size); !s.ok()) return s;
  timings.wall_ms = MsSince(t0);
  m.last_backward = timings;
  return absl::OkStatus();
}

const FieldLayout& VulkanField::layout() const { return impl_->layout; }
std::string VulkanField::device_description() const { return impl_->ctx->description(); }
bool VulkanField::is_cpu_device() const { return impl_->ctx->is_cpu(); }
bool VulkanField::uses_float_atomics() const { return impl_->float_atomics; }
int VulkanField::plane_buffers() const { return static_cast<int>(impl_->planes.size()); }
size_t VulkanField::batch_rows() const { return impl_->batch; }
const VulkanFieldTimings& VulkanField::last_forward() const { return impl_->last_forward; }
const VulkanFieldTimings& VulkanField::last_backward() const { return impl_->last_backward; }

}  // namespace streetsim::field
