// VulkanExtendedField: parameters on the device, the per-batch host round trip (ε, the encoder's
// geometry and their backward on the host), the batch's command buffer (token sampling:
// vk_token_sampler.h; network: ext_net.h).
#include "render/vulkan/field/ext/vulkan_extended_field.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <tuple>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "scene/field/extended/encoder_geometry.h"
#include "scene/field/extended/ext_noise.h"
#include "render/vulkan/field/ext/ext_net.h"
#include "render/vulkan/field/field_device_util.h"
#include "render/vulkan/field/ext/vk_token_sampler.h"
#include "render/vulkan/field/nn/vk_nn_kernels.h"

namespace streetsim::field {

namespace vk = vulkan;
using vkext::kOutCol0;
using vkext::kOutCols;
using vkext::kOutputs;
using vkext::kOutTotal;

namespace {

constexpr uint32_t kGeom = kEncoderGeometryInputs;

// One row of the encoder's geometry inputs (extended_field.cc's NetForward, in float).
void EncoderGeometryRow(const float* a, const float* b, const ExtInputs<float>& in, size_t g, float* row) {
  for (int k = 0; k < 3; ++k) row[k] = a[k] * in.means[g * 3 + k] + b[k];
  internal::GeometryInputs(in.opacity_logits[g], in.log_scales + g * 3, in.rotations + g * 4, row + 3);
}

absl::Status CheckModel(const ExtModel<float>& m) {
  if (!m.base_layout || !m.base_params || !m.config || !m.layout || (m.layout->total() > 0 && !m.ext_params)) {
    return absl::InvalidArgumentError("vulkan extended field: incomplete model");
  }
  if (m.layout->feature_dim != m.base_layout->feature_dim() || m.layout->model_dim != m.base_layout->width) {
    return absl::InvalidArgumentError("vulkan extended field: the extension's layout does not match the base field");
  }
  for (int k = 0; k < 3; ++k) {
    const double ext = m.aabb.max[k] - m.aabb.min[k];
    if (!std::isfinite(m.aabb.min[k]) || !std::isfinite(m.aabb.max[k]) || !(ext > 0)) {
      return absl::InvalidArgumentError("vulkan extended field: the AABB needs a finite positive extent per axis");
    }
  }
  return absl::OkStatus();
}

absl::Status CheckInputs(const ExtendedFieldConfig& c, const ExtInputs<float>& in) {
  if (in.n > 0 && !in.means) return absl::InvalidArgumentError("vulkan extended field: null means");
  if (in.n > 0 && c.encoder && (!in.opacity_logits || !in.log_scales || !in.rotations)) {
    return absl::InvalidArgumentError("vulkan extended field: the encoder needs opacities, scales and rotations");
  }
  return absl::OkStatus();
}

}  // namespace

struct VulkanExtendedField::Impl {
  // Declared first: destroyed last, after every buffer and pipeline of its device.
  std::unique_ptr<vk::Context> ctx;
  FieldLayout base_layout;
  ExtendedFieldConfig config;
  ExtendedLayout layout;
  FieldAabb aabb;
  VulkanFieldOptions options;
  std::unique_ptr<vknn::NnKernels> nn;
  std::unique_ptr<VkTokenSampler> sampler;
  std::unique_ptr<vkext::ExtNet> net;
  vk::Buffer mlp, ext, d_mlp, d_ext;
  size_t mlp_total = 0;
  uint32_t batch = 0;
  // Staging: means 3 | geometry 10 | ε L | token times K | output gradients 59 (per row, blocks
  // of `batch` rows). Readback: outputs 59 | KL 1 | dL/d(means) 3 | dL/d(geometry) 10.
  size_t st_geom = 0, st_eps = 0, st_times = 0, st_gout = 0;
  size_t rb_kl = 0, rb_dmeans = 0, rb_dgeom = 0;
  vk::Buffer staging, readback, grad_readback;
  FieldFrame frame;  // after the buffers: its destructor waits for the device first
  VulkanFieldTimings last_forward, last_backward;

  absl::Status Init(std::span<const float> base_params, std::span<const float> ext_params);
  absl::Status Upload(std::span<const float> base_params, std::span<const float> ext_params);
  // Fills the staging buffer's inputs for rows [b0, b0 + bn).
  void StageInputs(const ExtPass& pass, const ExtInputs<float>& in, size_t b0, size_t bn) const;
  void PoisonNonFiniteRows(const ExtInputs<float>& in, size_t b0, size_t bn, float* const dst[kOutputs]) const;
  // One batch [b0, b0 + bn): stage, record, submit, wait. Forward (d_out null): the outputs in
  // `flags` to the readback buffer; backward: flags = the outputs with a gradient, parameter
  // gradients accumulated on the device (zeroed first with zero_grads), dL/d(means) and
  // dL/d(geometry) to the readback buffer.
  absl::Status RunBatch(const ExtPass& pass, const ExtInputs<float>& in, size_t b0, size_t bn,
                        const bool flags[kOutputs], const ExtOutputGrads<float>* d_out, float kl_weight,
                        bool zero_grads, VulkanFieldTimings* timings);
  double SumKl(size_t bn) const;
};

absl::Status VulkanExtendedField::Impl::Init(std::span<const float> base_params, std::span<const float> ext_params) {
  const vk::Context& c = *ctx;
  auto kernels = vknn::NnKernels::Create(c);
  if (!kernels.ok()) return kernels.status();
  nn = *std::move(kernels);
  auto s = VkTokenSampler::Create(c, base_layout, layout.tokens, config.vae ? config.vae_dilation : 0,
                                  options.max_plane_buffer_bytes, options.force_cas_atomics);
  if (!s.ok()) return s.status();
  sampler = *std::move(s);
  net = std::make_unique<vkext::ExtNet>(c, *nn, base_layout, config, layout);
  // Batch: every per-row buffer within the device's range, every index within 32 bits.
  const size_t range = c.limits().maxStorageBufferRange;
  const size_t widest = net->WidestRow();
  const size_t b = std::min<size_t>({std::max<size_t>(options.batch_rows, 1), range / (widest * 4),
                                     (size_t{1} << 31) / (widest * 4)});
  if (b < 1) return absl::FailedPreconditionError("vulkan extended field: a single row exceeds the buffer range");
  batch = static_cast<uint32_t>(b);
  if (auto st = net->Allocate(batch); !st.ok()) return st;
  if (auto st = nn->Reserve(batch * static_cast<uint32_t>(layout.tokens), net->MaxParamFloats()); !st.ok()) return st;
  mlp_total = base_layout.total - base_layout.grid_size;
  for (auto [buf, floats, name] : {std::tuple{&mlp, mlp_total, "ext base mlp"}, {&d_mlp, mlp_total, "ext d_mlp"},
                                   {&ext, layout.total(), "ext params"}, {&d_ext, layout.total(), "ext d_params"}}) {
    auto nb = vk::Buffer::Create(c, std::max<size_t>(floats, 1) * 4, vk::Buffer::Kind::kDevice, name);
    if (!nb.ok()) return nb.status();
    *buf = *std::move(nb);
  }
  net->SetParams(&mlp, &ext);
  const size_t L = config.vae ? layout.vae.latent : 0, K = layout.tokens;
  st_geom = batch * size_t{3}, st_eps = st_geom + batch * size_t{kGeom}, st_times = st_eps + batch * L;
  st_gout = st_times + batch * K;
  rb_kl = batch * size_t{kOutTotal}, rb_dmeans = rb_kl + batch, rb_dgeom = rb_dmeans + batch * size_t{3};
  for (auto [buf, floats, kind, name] :
       {std::tuple{&staging, st_gout + batch * size_t{kOutTotal}, vk::Buffer::Kind::kStaging, "ext staging"},
        {&readback, rb_dgeom + batch * size_t{kGeom}, vk::Buffer::Kind::kReadback, "ext readback"}}) {
    auto nb = vk::Buffer::Create(c, floats * 4, kind, name);
    if (!nb.ok()) return nb.status();
    *buf = *std::move(nb);
  }
  if (auto st = frame.Create(c); !st.ok()) return st;
  return Upload(base_params, ext_params);
}

absl::Status VulkanExtendedField::Impl::Upload(std::span<const float> base_params, std::span<const float> ext_params) {
  if (base_params.size() != base_layout.total || ext_params.size() != layout.total()) {
    return absl::InvalidArgumentError(absl::StrCat("vulkan extended field: ", base_params.size(), " base and ",
                                                   ext_params.size(), " extension parameters, the layouts have ",
                                                   base_layout.total, " and ", layout.total()));
  }
  if (auto s = sampler->UploadPlanes(base_params); !s.ok()) return s;
  if (auto s = vk::UploadBytes(*ctx, mlp, base_params.data() + base_layout.grid_size, mlp_total * 4); !s.ok()) {
    return s;
  }
  if (ext_params.empty()) return absl::OkStatus();
  return vk::UploadBytes(*ctx, ext, ext_params.data(), ext_params.size() * 4);
}

// A non-finite encoder input (position, opacity, scale, rotation) makes the cpu's whole row NaN
// through the encoder's Linear. GPU compilers need not keep NaN through max/min/clamp (NVIDIA's
// relu turns it into 0, seen on an H100), so the device's row would be finite garbage that looks
// like a motion; the rule is made explicit on the host so both devices give NaN there.
void VulkanExtendedField::Impl::PoisonNonFiniteRows(const ExtInputs<float>& in, size_t b0, size_t bn,
                                                    float* const dst[kOutputs]) const {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  float row[kGeom];
  for (size_t r = 0; r < bn; ++r) {
    EncoderGeometryRow(sampler->nm_a(), sampler->nm_b(), in, b0 + r, row);
    if (std::all_of(row, row + kGeom, [](float v) { return std::isfinite(v); })) continue;
    for (int o = 0; o < kOutputs; ++o) {
      if (dst[o]) std::fill_n(dst[o] + (b0 + r) * kOutCols[o], kOutCols[o], nan);
    }
  }
}

void VulkanExtendedField::Impl::StageInputs(const ExtPass& pass, const ExtInputs<float>& in, size_t b0,
                                            size_t bn) const {
  float* st = static_cast<float*>(staging.mapped());
  std::memcpy(st, in.means + b0 * 3, bn * 3 * sizeof(float));
  if (config.encoder) {
    // The encoder's geometry inputs (extended_field.cc's NetForward, float).
    const float* a = sampler->nm_a();
    const float* b = sampler->nm_b();
    float* geom = st + st_geom;
    for (size_t r = 0; r < bn; ++r) EncoderGeometryRow(a, b, in, b0 + r, geom + r * kGeom);
  }
  if (config.vae && pass.training) {
    const int L = layout.vae.latent;
    float* eps = st + st_eps;
    for (size_t r = 0; r < bn; ++r)
      for (int i = 0; i < L; ++i) eps[r * L + i] = static_cast<float>(internal::Normal(pass.noise_seed, b0 + r, i));
  }
  if (config.temporal) {
    const int K = layout.tokens;
    float* times = st + st_times;
    for (size_t r = 0; r < bn; ++r) std::memcpy(times + r * K, sampler->token_times(), K * sizeof(float));
  }
}


absl::Status VulkanExtendedField::Impl::RunBatch(const ExtPass& pass, const ExtInputs<float>& in, size_t b0, size_t bn,
                                                 const bool flags[kOutputs], const ExtOutputGrads<float>* d_out,
                                                 float kl_weight, bool zero_grads, VulkanFieldTimings* timings) {
  const bool backward = d_out != nullptr;
  const uint32_t rows = static_cast<uint32_t>(bn);
  const uint32_t D = layout.feature_dim, K = layout.tokens, L = config.vae ? layout.vae.latent : 0;
  StageInputs(pass, in, b0, bn);
  const float* gsrc[kOutputs] = {};
  if (backward) {
    const float* g[kOutputs] = {d_out->d_dx, d_out->d_dsh, d_out->d_dscale, d_out->d_drot, d_out->d_dopacity};
    float* st = static_cast<float*>(staging.mapped()) + st_gout;
    for (int o = 0; o < kOutputs; ++o) {
      if (!flags[o]) continue;
      gsrc[o] = g[o];
      std::memcpy(st + size_t{batch} * kOutCol0[o], g[o] + b0 * kOutCols[o], bn * kOutCols[o] * sizeof(float));
    }
  }
  vk::Recorder rec(*ctx, frame.cmd, frame.arena.get());
  if (auto s = frame.Begin(rec); !s.ok()) return s;
  if (zero_grads) {
    sampler->RecordZeroGrads(rec);
    rec.Fill(d_mlp, 0, VK_WHOLE_SIZE, 0);
    rec.Fill(d_ext, 0, VK_WHOLE_SIZE, 0);
  }
  auto up = [&](size_t st_off, const char* name, size_t floats) {
    rec.Copy(staging, st_off * 4, net->buf(name), 0, floats * 4);
  };
  up(0, "means", bn * 3);
  if (config.encoder) up(st_geom, "geom", bn * kGeom);
  if (config.vae && pass.training) up(st_eps, "eps", bn * L);
  if (config.temporal) up(st_times, "times", bn * K);
  for (int o = 0; o < kOutputs; ++o) {
    if (gsrc[o]) {
      rec.Copy(staging, (st_gout + size_t{batch} * kOutCol0[o]) * 4, net->buf("gout"), size_t{batch} * kOutCol0[o] * 4,
               bn * kOutCols[o] * 4);
    }
  }
  rec.Barrier();
  frame.WriteTimestamp(0);
  const vk::Buffer& means = net->buf("means");
  VkTokenSampler::SView s_view;
  if (config.encoder) s_view = {&net->buf("xenc"), kGeom, kGeom + D, &net->buf("geom"), kGeom};
  sampler->RecordForward(rec, rows, means, s_view, net->buf("ftok"), net->sdil());
  rec.Barrier();
  net->RecordForward(rec, rows, pass.training, flags);
  if (backward) {
    net->RecordBackward(rec, rows, pass.training, kl_weight, flags, mlp, ext, d_mlp, d_ext);
    VkTokenSampler::SView ds_view;
    if (config.encoder) ds_view = {&net->buf("dxenc"), kGeom, kGeom + D, nullptr, 0};
    sampler->RecordBackward(rec, rows, means, ds_view, net->dftok(), net->dsdil(), net->buf("d_means"));
    rec.Barrier();
  }
  frame.WriteTimestamp(1);
  if (!backward) {
    for (int o = 0; o < kOutputs; ++o) {
      if (flags[o]) {
        const size_t off = size_t{batch} * kOutCol0[o] * 4;
        rec.Copy(net->buf("out"), off, readback, off, bn * kOutCols[o] * 4);
      }
    }
  } else {
    rec.Copy(net->buf("d_means"), 0, readback, rb_dmeans * 4, bn * 3 * 4);
    if (config.encoder) {
      // The geometry columns of dL/d(encoder input), row by row.
      std::vector<VkBufferCopy> regions(bn);
      for (size_t r = 0; r < bn; ++r) regions[r] = {r * (kGeom + D) * 4, (rb_dgeom + r * kGeom) * 4, kGeom * 4};
      if (rec.status().ok()) {
        vkCmdCopyBuffer(frame.cmd, net->buf("dxenc").handle(), readback.handle(), static_cast<uint32_t>(bn),
                        regions.data());
      }
    }
  }
  if (config.vae) rec.Copy(net->buf("kl"), 0, readback, rb_kl * 4, bn * 4);
  if (auto s = frame.SubmitAndWait(rec, readback); !s.ok()) return s;
  timings->device_ms += frame.ReadTimestampsMs();
  ++timings->batches;
  return absl::OkStatus();
}

double VulkanExtendedField::Impl::SumKl(size_t bn) const {
  if (!config.vae) return 0;
  const float* kl = static_cast<const float*>(readback.mapped()) + rb_kl;
  double sum = 0;
  for (size_t r = 0; r < bn; ++r) sum += kl[r];
  return sum;
}

VulkanExtendedField::VulkanExtendedField(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
VulkanExtendedField::~VulkanExtendedField() = default;

absl::StatusOr<std::unique_ptr<VulkanExtendedField>> VulkanExtendedField::Create(const ExtModel<float>& model,
                                                                                 const VulkanFieldOptions& options) {
  if (auto s = CheckModel(model); !s.ok()) return s;
  if (model.layout->tokens > kVkMaxTokens) {
    return absl::FailedPreconditionError(absl::StrCat("vulkan extended field: ", model.layout->tokens,
                                                      " tokens, the kernels take at most ", kVkMaxTokens));
  }
  auto impl = std::make_unique<Impl>();
  auto ctx = vk::Context::Create(options.device);
  if (!ctx.ok()) return ctx.status();
  impl->ctx = *std::move(ctx);
  impl->base_layout = *model.base_layout;
  impl->config = *model.config;
  impl->layout = *model.layout;
  impl->aabb = model.aabb;
  impl->options = options;
  const std::span<const float> base(model.base_params, model.base_layout->total);
  const std::span<const float> ext(model.ext_params, model.ext_params ? model.layout->total() : 0);
  if (auto s = impl->Init(base, ext); !s.ok()) return s;
  return std::unique_ptr<VulkanExtendedField>(new VulkanExtendedField(std::move(impl)));
}

absl::StatusOr<std::unique_ptr<VulkanExtendedField>> VulkanExtendedField::Create(const ExtendedField& field,
                                                                                 const VulkanFieldOptions& options) {
  return Create(ModelOf(field), options);
}

absl::Status VulkanExtendedField::UpdateParams(std::span<const float> base_params, std::span<const float> ext_params) {
  return impl_->Upload(base_params, ext_params);
}

absl::StatusOr<double> VulkanExtendedField::Forward(const ExtPass& pass, const ExtInputs<float>& in,
                                                    const ExtOutputs<float>& out) {
  Impl& m = *impl_;
  const auto t0 = std::chrono::steady_clock::now();
  if (auto s = CheckInputs(m.config, in); !s.ok()) return s;
  m.sampler->SetPass(m.aabb, pass.time_coord, m.config.temporal ? m.config.window_dt : 0.0);
  float* dst[kOutputs] = {out.dx, out.dsh, m.config.decoder ? out.dscale : nullptr,
                          m.config.decoder ? out.drot : nullptr, m.config.decoder ? out.dopacity : nullptr};
  bool wanted[kOutputs];
  for (int o = 0; o < kOutputs; ++o) wanted[o] = dst[o] != nullptr;
  VulkanFieldTimings timings;
  double kl = 0;
  for (size_t b0 = 0; b0 < in.n; b0 += m.batch) {
    const size_t bn = std::min<size_t>(m.batch, in.n - b0);
    if (auto s = m.RunBatch(pass, in, b0, bn, wanted, nullptr, 0.f, false, &timings); !s.ok()) return s;
    const float* rb = static_cast<const float*>(m.readback.mapped());
    for (int o = 0; o < kOutputs; ++o) {
      if (wanted[o]) {
        std::memcpy(dst[o] + b0 * kOutCols[o], rb + size_t{m.batch} * kOutCol0[o], bn * kOutCols[o] * sizeof(float));
      }
    }
    if (m.config.encoder) m.PoisonNonFiniteRows(in, b0, bn, dst);
    kl += m.SumKl(bn);
  }
  timings.wall_ms = MsSince(t0);
  m.last_forward = timings;
  return kl;
}

absl::StatusOr<double> VulkanExtendedField::Backward(const ExtPass& pass, const ExtInputs<float>& in,
                                                     const ExtOutputGrads<float>& d_out, double kl_weight,
                                                     const ExtInputGrads<float>& grads) {
  Impl& m = *impl_;
  const auto t0 = std::chrono::steady_clock::now();
  if (auto s = CheckInputs(m.config, in); !s.ok()) return s;
  if (!grads.d_base || (!grads.d_ext && m.layout.total() > 0)) {
    return absl::InvalidArgumentError("vulkan extended field backward: null parameter gradients");
  }
  m.sampler->SetPass(m.aabb, pass.time_coord, m.config.temporal ? m.config.window_dt : 0.0);
  bool present[kOutputs] = {d_out.d_dx != nullptr, d_out.d_dsh != nullptr,
                            m.config.decoder && d_out.d_dscale != nullptr, m.config.decoder && d_out.d_drot != nullptr,
                            m.config.decoder && d_out.d_dopacity != nullptr};
  VulkanFieldTimings timings;
  double kl = 0;
  if (in.n == 0) {
    m.last_backward = timings;
    return 0.0;
  }
  const float* a = m.sampler->nm_a();
  for (size_t b0 = 0; b0 < in.n; b0 += m.batch) {
    const size_t bn = std::min<size_t>(m.batch, in.n - b0);
    if (auto s = m.RunBatch(pass, in, b0, bn, present, &d_out, static_cast<float>(kl_weight), b0 == 0, &timings);
        !s.ok()) {
      return s;
    }
    const float* rb = static_cast<const float*>(m.readback.mapped());
    if (grads.d_means) {
      const float* dm = rb + m.rb_dmeans;
      for (size_t i = 0; i < bn * 3; ++i) grads.d_means[b0 * 3 + i] += dm[i];
    }
    if (m.config.encoder) {
      // The encoder's geometry inputs, back to the canonical Gaussians (encoder_geometry.h).
      const float* dg = rb + m.rb_dgeom;
      for (size_t r = 0; r < bn; ++r) {
        const size_t g = b0 + r;
        const float* row = dg + r * kGeom;
        if (grads.d_means)
          for (int k = 0; k < 3; ++k) grads.d_means[g * 3 + k] += row[k] * a[k];
        internal::GeometryInputsBackward(in.opacity_logits[g], in.log_scales + g * 3, in.rotations + g * 4, row + 3,
                                         grads.d_opacity_logits ? grads.d_opacity_logits + g : nullptr,
                                         grads.d_log_scales ? grads.d_log_scales + g * 3 : nullptr,
                                         grads.d_rotations ? grads.d_rotations + g * 4 : nullptr);
      }
    }
    kl += m.SumKl(bn);
  }
  if (auto s = m.sampler->DownloadAddGrads(&m.grad_readback, grads.d_base); !s.ok()) return s;
  if (auto s = DownloadAdd(*m.ctx, m.d_mlp, m.mlp_total, &m.grad_readback, grads.d_base + m.base_layout.grid_size);
      !s.ok()) {
    return s;
  }
  if (m.layout.total() > 0) {
    if (auto s = DownloadAdd(*m.ctx, m.d_ext, m.layout.total(), &m.grad_readback, grads.d_ext); !s.ok()) return s;
  }
  timings.wall_ms = MsSince(t0);
  m.last_backward = timings;
  return kl;
}

std::string VulkanExtendedField::device_description() const { return impl_->ctx->description(); }
bool VulkanExtendedField::is_cpu_device() const { return impl_->ctx->is_cpu(); }
bool VulkanExtendedField::uses_float_atomics() const { return impl_->sampler->uses_float_atomics(); }
int VulkanExtendedField::plane_buffers() const { return impl_->sampler->plane_buffers(); }
size_t VulkanExtendedField::batch_rows() const { return impl_->batch; }
const VulkanFieldTimings& VulkanExtendedField::last_forward() const { return impl_->last_forward; }
const VulkanFieldTimings& VulkanExtendedField::last_backward() const { return impl_->last_backward; }

}  // namespace streetsim::field
