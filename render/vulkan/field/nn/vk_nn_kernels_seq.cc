// NnKernels' row ops (LayerNorm), temporal tokens, VAE, attention core and GRU step: the shaders
// nn_layer_norm.comp, nn_fourier.comp, nn_vae.comp, nn_attention.comp, nn_gru.comp.
#include <cmath>

#include "absl/strings/str_cat.h"
#include "render/vulkan/field/nn/vk_nn_impl.h"
#include "streetsim_spirv.h"

namespace streetsim::field::vknn {

namespace vk = vulkan;

namespace {

constexpr uint32_t kLayerNormRowsPerWg = 8;  // nn_layer_norm.comp: ROWS_PER_WG
// nn_attention.comp's loops run about 3 T (head_dim + 1) times per invocation; lavapipe stops an
// invocation's loops after 65 535 iterations in total.
constexpr uint64_t kMaxAttentionIterations = 60000;

// The shaders' push constants: sizes, then (offset, stride) per view in the shader's order.
struct LayerNormPush {
  uint32_t rows, dim, backward, g_off, b_off;
  float eps;
  OffStride x, y, h, r, d;
};
struct FourierPush {
  uint32_t rows, tokens, m, F, backward;
  OffStride t, s, o;
};
struct VaePush {
  uint32_t rows, L, backward, has_eps;
  float kl_weight;
  OffStride m, e, z, k;
};
struct AttentionPush {
  uint32_t rows, T, H, dh, backward;
  float scale;
  OffStride q, k, v, a, o, dq, dk, dv;
};
struct GruPush {
  uint32_t rows, H, backward;
  OffStride gi, gh, hp, g, h, dgi, dgh, dhp;
};

bool Positive(vk::Recorder& rec, const char* op, std::initializer_list<int> sizes) {
  for (int s : sizes) {
    if (s <= 0) {
      rec.Fail(absl::InvalidArgumentError(absl::StrCat("vk nn ", op, ": sizes must be positive")));
      return false;
    }
  }
  return true;
}

}  // namespace

absl::Status CreateSeqPipelines(NnKernels::Impl& m) {
  const vk::PipelineSpec specs[] = {
      {&m.layer_norm, "nn_layer_norm", spirv::nn_layer_norm, 6, sizeof(LayerNormPush), {}},
      {&m.fourier, "nn_fourier", spirv::nn_fourier, 3, sizeof(FourierPush), {}},
      {&m.vae, "nn_vae", spirv::nn_vae, 4, sizeof(VaePush), {}},
      {&m.attention, "nn_attention", spirv::nn_attention, 8, sizeof(AttentionPush), {}},
      {&m.gru, "nn_gru", spirv::nn_gru, 8, sizeof(GruPush), {}},
  };
  return vk::CreatePipelines(*m.ctx, specs);
}

// ---- LayerNorm ----

void NnKernels::LayerNorm(vk::Recorder& rec, const nn::LayerNormSpec& s, const vk::Buffer& params, View x, View y,
                          View xhat, View rstd) {
  const Impl& m = *impl_;
  const uint32_t dim = static_cast<uint32_t>(s.dim), R = x.rows;
  if (!Positive(rec, "layer norm", {s.dim}) ||
      !m.CheckViews(rec, "layer norm", {{"x", x}, {"y", y}, {"xhat", xhat}, {"rstd", rstd}}) ||
      !m.CheckShape(rec, "layer norm", {"x", x}, R, dim) || !m.CheckShape(rec, "layer norm", {"y", y}, R, dim) ||
      !m.CheckShape(rec, "layer norm", {"xhat", xhat}, R, dim) ||
      !m.CheckShape(rec, "layer norm", {"rstd", rstd}, R, 1) ||
      !m.CheckParams(rec, "layer norm", "gain", params, s.gain_offset, dim) ||
      !m.CheckParams(rec, "layer norm", "bias", params, s.bias_offset, dim)) {
    return;
  }
  if (R == 0) return;
  const uint32_t g_off = static_cast<uint32_t>(s.gain_offset), b_off = static_cast<uint32_t>(s.bias_offset);
  const LayerNormPush push{R, dim, 0, g_off, b_off, static_cast<float>(s.eps), Os(x), Os(y), Os(xhat), Os(rstd), {}};
  rec.Dispatch(*m.layer_norm, {x.buffer, &params, y.buffer, xhat.buffer, rstd.buffer, x.buffer}, push,
               vk::GridFor(DivUp(R, kLayerNormRowsPerWg)));
}

void NnKernels::LayerNormGrad(vk::Recorder& rec, const nn::LayerNormSpec& s, const vk::Buffer& params, View xhat,
                              View rstd, View dy, View dx, const vk::Buffer& d_params) {
  const Impl& m = *impl_;
  const uint32_t dim = static_cast<uint32_t>(s.dim), R = xhat.rows;
  if (!Positive(rec, "layer norm grad", {s.dim}) ||
      !m.CheckViews(rec, "layer norm grad", {{"xhat", xhat}, {"rstd", rstd}, {"dy", dy}, {"dx", dx}}) ||
      !m.CheckShape(rec, "layer norm grad", {"xhat", xhat}, R, dim) ||
      !m.CheckShape(rec, "layer norm grad", {"rstd", rstd}, R, 1) ||
      !m.CheckShape(rec, "layer norm grad", {"dy", dy}, R, dim) ||
      !m.CheckShape(rec, "layer norm grad", {"dx", dx}, R, dim) ||
      !m.CheckParams(rec, "layer norm grad", "gain", params, s.gain_offset, dim) ||
      !m.CheckParams(rec, "layer norm grad", "d gain", d_params, s.gain_offset, dim) ||
      !m.CheckParams(rec, "layer norm grad", "d bias", d_params, s.bias_offset, dim) ||
      !m.CheckScratch(rec, "layer norm grad", R, 2 * uint64_t{dim})) {
    return;
  }
  if (R == 0) return;
  // Gain and bias partials (columns [0, dim) and [dim, 2 dim) of each chunk's block) before dx is
  // written: dx may be dy.
  m.ColSumPartials(rec, dy, &xhat, 0, 2 * dim);
  m.ColSumPartials(rec, dy, nullptr, dim, 2 * dim);
  rec.Barrier();
  const LayerNormPush push{R,  dim,      1,     static_cast<uint32_t>(s.gain_offset), 0, 0.0f, Os(xhat), Os(dx),
                           {}, Os(rstd), Os(dy)};
  rec.Dispatch(*m.layer_norm, {xhat.buffer, &params, dx.buffer, xhat.buffer, rstd.buffer, dy.buffer}, push,
               vk::GridFor(DivUp(R, kLayerNormRowsPerWg)));
  m.Reduce(rec, R, dim, 0, 2 * dim, d_params, static_cast<uint32_t>(s.gain_offset));
  m.Reduce(rec, R, dim, dim, 2 * dim, d_params, static_cast<uint32_t>(s.bias_offset));
  rec.Barrier();
}

// ---- Temporal tokens ----

void NnKernels::FourierTokens(vk::Recorder& rec, const nn::FourierTimeSpec& s, View times, View features, View tokens) {
  const Impl& m = *impl_;
  const uint32_t T = static_cast<uint32_t>(s.tokens), F = static_cast<uint32_t>(s.feature_dim),
                 D = static_cast<uint32_t>(s.token_dim()), B = times.rows;
  if (!Positive(rec, "fourier tokens", {s.tokens, s.token_dim()}) || s.frequencies < 0 || s.feature_dim < 0 ||
      !m.CheckViews(rec, "fourier tokens", {{"times", times}, {"features", features}, {"tokens", tokens}}) ||
      !m.CheckShape(rec, "fourier tokens", {"times", times}, B, T) ||
      !m.CheckShape(rec, "fourier tokens", {"features", features}, B, T * F) ||
      !m.CheckShape(rec, "fourier tokens", {"tokens", tokens}, B, T * D)) {
    if (rec.status().ok()) rec.Fail(absl::InvalidArgumentError("vk nn fourier tokens: bad spec"));
    return;
  }
  if (B == 0) return;
  const FourierPush push{B, T, static_cast<uint32_t>(s.frequencies), F, 0, Os(times), Os(features), Os(tokens)};
  rec.Dispatch(*m.fourier, {times.buffer, features.buffer, tokens.buffer}, push,
               vk::GridFor(DivUp(uint64_t{B} * T * D, kWg)));
}

void NnKernels::FourierTokensGrad(vk::Recorder& rec, const nn::FourierTimeSpec& s, View d_tokens, View d_features) {
  const Impl& m = *impl_;
  const uint32_t T = static_cast<uint32_t>(s.tokens), F = static_cast<uint32_t>(s.feature_dim),
                 D = static_cast<uint32_t>(s.token_dim()), B = d_tokens.rows;
  if (!Positive(rec, "fourier tokens grad", {s.tokens, s.token_dim()}) || s.frequencies < 0 || s.feature_dim < 0 ||
      !m.CheckViews(rec, "fourier tokens grad", {{"d_tokens", d_tokens}, {"d_features", d_features}}) ||
      !m.CheckShape(rec, "fourier tokens grad", {"d_tokens", d_tokens}, B, T * D) ||
      !m.CheckShape(rec, "fourier tokens grad", {"d_features", d_features}, B, T * F)) {
    if (rec.status().ok()) rec.Fail(absl::InvalidArgumentError("vk nn fourier tokens grad: bad spec"));
    return;
  }
  if (B == 0 || F == 0) return;
  const FourierPush push{B, T, static_cast<uint32_t>(s.frequencies), F, 1, {}, Os(d_tokens), Os(d_features)};
  rec.Dispatch(*m.fourier, {d_tokens.buffer, d_tokens.buffer, d_features.buffer}, push,
               vk::GridFor(DivUp(uint64_t{B} * T * F, kWg)));
}

// ---- VAE ----

namespace {

// mu_logvar [B, 2L] and, when it has a buffer, eps [B, L].
bool CheckVaeInputs(const NnKernels::Impl& m, vk::Recorder& rec, const char* op, int latent, View mu_logvar, View eps) {
  const uint32_t L = static_cast<uint32_t>(latent), B = mu_logvar.rows;
  const bool has_eps = eps.buffer != nullptr;
  return Positive(rec, op, {latent}) && m.CheckViews(rec, op, {{"mu_logvar", mu_logvar}}) &&
         m.CheckShape(rec, op, {"mu_logvar", mu_logvar}, B, 2 * L) &&
         (!has_eps || (m.CheckViews(rec, op, {{"eps", eps}}) && m.CheckShape(rec, op, {"eps", eps}, B, L)));
}

}  // namespace

void NnKernels::VaeSample(vk::Recorder& rec, int latent, View mu_logvar, View eps, View z, View kl) {
  const Impl& m = *impl_;
  const uint32_t L = static_cast<uint32_t>(latent), B = mu_logvar.rows;
  const bool has_eps = eps.buffer != nullptr;
  if (!CheckVaeInputs(m, rec, "vae sample", latent, mu_logvar, eps) ||
      !m.CheckViews(rec, "vae sample", {{"z", z}, {"kl", kl}}) || !m.CheckShape(rec, "vae sample", {"z", z}, B, L) ||
      !m.CheckShape(rec, "vae sample", {"kl", kl}, B, 1)) {
    return;
  }
  if (B == 0) return;
  const VaePush push{B, L, 0, has_eps ? 1u : 0u, 0.0f, Os(mu_logvar), Os(eps), Os(z), Os(kl)};
  rec.Dispatch(*m.vae, {mu_logvar.buffer, has_eps ? eps.buffer : mu_logvar.buffer, z.buffer, kl.buffer}, push,
               vk::GridFor(DivUp(B, kWg)));
}

void NnKernels::VaeSampleGrad(vk::Recorder& rec, int latent, View mu_logvar, View eps, View dz, float kl_weight,
                              View d_mu_logvar) {
  const Impl& m = *impl_;
  const uint32_t L = static_cast<uint32_t>(latent), B = mu_logvar.rows;
  const bool has_eps = eps.buffer != nullptr;
  if (!CheckVaeInputs(m, rec, "vae sample grad", latent, mu_logvar, eps) ||
      !m.CheckViews(rec, "vae sample grad", {{"dz", dz}, {"d_mu_logvar", d_mu_logvar}}) ||
      !m.CheckShape(rec, "vae sample grad", {"dz", dz}, B, L) ||
      !m.CheckShape(rec, "vae sample grad", {"d_mu_logvar", d_mu_logvar}, B, 2 * L)) {
    return;
  }
  if (B == 0) return;
  const VaePush push{B, L, 1, has_eps ? 1u : 0u, kl_weight, Os(mu_logvar), Os(eps), Os(dz), Os(d_mu_logvar)};
  rec.Dispatch(*m.vae, {mu_logvar.buffer, has_eps ? eps.buffer : mu_logvar.buffer, dz.buffer, d_mu_logvar.buffer}, push,
               vk::GridFor(DivUp(uint64_t{B} * L, kWg)));
}

// ---- Attention core ----

namespace {

bool CheckAttentionSizes(vk::Recorder& rec, const char* op, int tokens, int heads, int head_dim) {
  if (!Positive(rec, op, {tokens, heads, head_dim})) return false;
  const uint64_t iterations = 3 * uint64_t(tokens) * (uint64_t(head_dim) + 1) + uint64_t(head_dim);
  if (iterations > kMaxAttentionIterations) {
    rec.Fail(absl::InvalidArgumentError(
        absl::StrCat("vk nn ", op, ": ", tokens, " tokens x head_dim ", head_dim,
                     " is past the kernel's loop budget (3 T (head_dim + 1) <= ", kMaxAttentionIterations, ")")));
    return false;
  }
  return true;
}

}  // namespace

namespace {

// The forward (grads null: O written) or the backward (O is dO; dQ, dK, dV written).
void RecordAttention(const NnKernels::Impl& m, vk::Recorder& rec, const char* op, int tokens, int heads, int head_dim,
                     View Q, View K, View V, View A, View O, const View* dQ, const View* dK, const View* dV) {
  if (!CheckAttentionSizes(rec, op, tokens, heads, head_dim)) return;
  const uint32_t T = tokens, H = heads, M = static_cast<uint32_t>(heads * head_dim), B = Q.rows;
  const bool backward = dQ != nullptr;
  const char* o_name = backward ? "dO" : "O";
  if (!m.CheckViews(rec, op, {{"Q", Q}, {"K", K}, {"V", V}, {"A", A}, {o_name, O}}) ||
      !m.CheckShape(rec, op, {"Q", Q}, B, M) || !m.CheckShape(rec, op, {"K", K}, B * T, M) ||
      !m.CheckShape(rec, op, {"V", V}, B * T, M) || !m.CheckShape(rec, op, {"A", A}, B, H * T) ||
      !m.CheckShape(rec, op, {o_name, O}, B, M)) {
    return;
  }
  if (backward &&
      (!m.CheckViews(rec, op, {{"dQ", *dQ}, {"dK", *dK}, {"dV", *dV}}) || !m.CheckShape(rec, op, {"dQ", *dQ}, B, M) ||
       !m.CheckShape(rec, op, {"dK", *dK}, B * T, M) || !m.CheckShape(rec, op, {"dV", *dV}, B * T, M))) {
    return;
  }
  if (B == 0) return;
  const View& q = backward ? *dQ : O;  // unused bindings of the forward: O
  const View& k = backward ? *dK : O;
  const View& v = backward ? *dV : O;
  const float scale = 1.0f / std::sqrt(static_cast<float>(head_dim));  // as the cpu, in float
  const AttentionPush push{
      B,     T,     H,    static_cast<uint32_t>(head_dim), backward ? 1u : 0u, scale, Os(Q), Os(K), Os(V), Os(A), Os(O),
      Os(q), Os(k), Os(v)};
  rec.Dispatch(*m.attention, {Q.buffer, K.buffer, V.buffer, A.buffer, O.buffer, q.buffer, k.buffer, v.buffer}, push,
               vk::GridFor(DivUp(uint64_t{B} * H, kWg)));
}

}  // namespace

void NnKernels::AttentionCore(vk::Recorder& rec, int tokens, int heads, int head_dim, View Q, View K, View V, View A,
                              View O) {
  RecordAttention(*impl_, rec, "attention", tokens, heads, head_dim, Q, K, V, A, O, nullptr, nullptr, nullptr);
}

void NnKernels::AttentionCoreGrad(vk::Recorder& rec, int tokens, int heads, int head_dim, View Q, View K, View V,
                                  View A, View dO, View dQ, View dK, View dV) {
  RecordAttention(*impl_, rec, "attention grad", tokens, heads, head_dim, Q, K, V, A, dO, &dQ, &dK, &dV);
}

// ---- GRU step ----

void NnKernels::GruStep(vk::Recorder& rec, int hidden, View gi, View gh, View h_prev, View h, View rzn) {
  const Impl& m = *impl_;
  const uint32_t H = static_cast<uint32_t>(hidden), B = h_prev.rows;
  if (!Positive(rec, "gru", {hidden}) ||
      !m.CheckViews(rec, "gru", {{"gi", gi}, {"gh", gh}, {"h_prev", h_prev}, {"h", h}, {"rzn", rzn}}) ||
      !m.CheckShape(rec, "gru", {"gi", gi}, B, 3 * H) || !m.CheckShape(rec, "gru", {"gh", gh}, B, 3 * H) ||
      !m.CheckShape(rec, "gru", {"h_prev", h_prev}, B, H) || !m.CheckShape(rec, "gru", {"h", h}, B, H) ||
      !m.CheckShape(rec, "gru", {"rzn", rzn}, B, 3 * H)) {
    return;
  }
  if (B == 0) return;
  const GruPush push{B, H, 0, Os(gi), Os(gh), Os(h_prev), Os(rzn), Os(h), {}, {}, {}};
  rec.Dispatch(*m.gru, {gi.buffer, gh.buffer, h_prev.buffer, rzn.buffer, h.buffer, h.buffer, h.buffer, h.buffer}, push,
               vk::GridFor(DivUp(uint64_t{B} * H, kWg)));
}

void NnKernels::GruStepGrad(vk::Recorder& rec, int hidden, View gh, View rzn, View h_prev, View dh, View dgi, View dgh,
                            View dh_prev) {
  const Impl& m = *impl_;
  const uint32_t H = static_cast<uint32_t>(hidden), B = h_prev.rows;
  const char* op = "gru grad";
  if (!Positive(rec, op, {hidden}) ||
      !m.CheckViews(rec, op,
                    {{"gh", gh},
                     {"rzn", rzn},
                     {"h_prev", h_prev},
                     {"dh", dh},
                     {"dgi", dgi},
                     {"dgh", dgh},
                     {"dh_prev", dh_prev}}) ||
      !m.CheckShape(rec, op, {"gh", gh}, B, 3 * H) || !m.CheckShape(rec, op, {"rzn", rzn}, B, 3 * H) ||
      !m.CheckShape(rec, op, {"h_prev", h_prev}, B, H) || !m.CheckShape(rec, op, {"dh", dh}, B, H) ||
      !m.CheckShape(rec, op, {"dgi", dgi}, B, 3 * H) || !m.CheckShape(rec, op, {"dgh", dgh}, B, 3 * H) ||
      !m.CheckShape(rec, op, {"dh_prev", dh_prev}, B, H)) {
    return;
  }
  if (B == 0) return;
  const GruPush push{B, H, 1, {}, Os(gh), Os(h_prev), Os(rzn), Os(dh), Os(dgi), Os(dgh), Os(dh_prev)};
  rec.Dispatch(*m.gru,
               {gh.buffer, gh.buffer, h_prev.buffer, rzn.buffer, dh.buffer, dgi.buffer, dgh.buffer, dh_prev.buffer},
               push, vk::GridFor(DivUp(uint64_t{B} * H, kWg)));
}

}  // namespace streetsim::field::vknn
