#include "scene/field/extended/extended_field.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "scene/field/extended/encoder_geometry.h"
#include "scene/field/extended/ext_noise.h"
#include "scene/field/extended/extended_sampling.h"

namespace streetsim::field {

namespace {

using nn::ConstRef;
using nn::Mat;

constexpr int64_t kRowsPerChunk = 128;       // forward rows per task
constexpr int64_t kBackwardRowsPerChunk = 64;
constexpr size_t kBackwardBlock = 2048;      // rows whose plane gradients are scattered together

// S3Gaussian's trunk and heads as nn::LinearSpec over the base MLP (offsets relative to the end of
// the grid, so that per-thread gradients need only the MLP's size).
struct BaseMlp {
  nn::LinearSpec trunk, pos1, pos2, sh1, sh2;
  explicit BaseMlp(const FieldLayout& L) {
    auto spec = [&](const DenseInfo& d) {
      nn::LinearSpec s;
      s.in = d.in;
      s.out = d.out;
      s.w_offset = d.w_offset - L.grid_size;
      s.b_offset = d.b_offset - L.grid_size;
      return s;
    };
    trunk = spec(L.trunk), pos1 = spec(L.pos1), pos2 = spec(L.pos2), sh1 = spec(L.sh1), sh2 = spec(L.sh2);
  }
};

using internal::Normal;  // ε (ext_noise.h)

template <typename T>
struct Scratch {
  // Sampling.
  Mat<T> S, Ftok, F;  // [B, D] spatial product, [B, K*D] per-token features, [B, D] centre token
  Mat<T> Sdil;        // [B, D] dilated spatial product (VAE variance branch)
  std::vector<internal::Tap<T>> taps;  // sampling scratch
  std::vector<T> tbuf;
  // Network.
  Mat<T> H0, H, Arelu, P1, Sh1, X1, R1, O1, q0, q, r, Tok, times;
  Mat<T> Xenc, ML, eps, z, attn_out, gru_out, tmp;
  Mat<T> mu, lv;  // dilated VAE: the two halves of ML before they are joined
  std::vector<Mat<T>> enc_z, enc_n, enc_a;  // per encoder layer: linear out, norm out, activation out
  Mat<T> E0;
  std::vector<nn::LayerNormCache<T>> ln_cache;
  std::vector<nn::ActivationCache<T>> act_cache;
  nn::VaeCache<T> vae_cache;
  nn::FourierTimeCache<T> fourier_cache;
  nn::AttentionCache<T> attn_cache;
  nn::BiGruCache<T> gru_cache;
  // Backward.
  Mat<T> dSdil;
  Mat<T> dH, dr, dA, dP1, dSh1, dX1, dR1, dO1, dq, dq0, dTok, dTok2, dq2, dML, dz, dF, dFtok, dX, dE, dN, dZ;
  std::vector<T> base_grad, ext_grad;  // per thread, [base MLP], [extension]
  double kl = 0;
  absl::Status status;
};

template <typename T>
struct WorkspaceT {
  std::vector<Scratch<T>> threads;
  std::vector<T> samples;                    // [slots * block * C], slot-major (SlotStore)
  std::vector<internal::PlaneTaps<T>> taps;  // [slots * block]
  void Reserve(int n) {
    if (static_cast<int>(threads.size()) < n) threads.resize(n);
  }
};

template <typename T>
struct Ctx {
  const ExtModel<T>& m;
  const ExtendedFieldConfig& c;
  const ExtendedLayout& L;
  const FieldLayout& BL;
  BaseMlp base;
  internal::TokenSampler<T> sampler;
  const T* bp_mlp;  // base params from the MLP on
  Ctx(const ExtModel<T>& model, const ExtPass& pass)
      : m(model), c(*model.config), L(*model.layout), BL(*model.base_layout), base(*model.base_layout),
        sampler(*model.base_layout, model.base_params, model.aabb, pass.time_coord, model.config->tokens(),
                model.config->temporal ? model.config->window_dt : 0.0,
                model.config->vae ? model.config->vae_dilation : 0),
        bp_mlp(model.base_params + model.base_layout->grid_size) {}
};

#define EXT_RETURN_IF_ERROR(expr)           \
  do {                                      \
    absl::Status _s = (expr);               \
    if (!_s.ok()) return _s;                \
  } while (0)

template <typename T>
void Relu(Mat<T>* x) {
  *x = x->cwiseMax(T(0));
}
template <typename T>
void ReluMask(const Mat<T>& y, Mat<T>* d) {
  d->array() *= (y.array() > T(0)).template cast<T>();
}

// Network forward for the chunk [b, e) whose features are in sc.S / sc.Ftok. Writes outputs.
template <typename T>
absl::Status NetForward(const Ctx<T>& x, const ExtPass& pass, const ExtInputs<T>& in, int64_t b, int64_t e,
                        Scratch<T>& sc, const ExtOutputs<T>* out) {
  const ExtendedFieldConfig& c = x.c;
  const ExtendedLayout& L = x.L;
  const T* ep = x.m.ext_params;
  const int64_t B = e - b;
  const int D = L.feature_dim, K = L.tokens, kc = c.center_token();
  sc.F = sc.Ftok.middleCols(static_cast<Eigen::Index>(kc) * D, D);
  EXT_RETURN_IF_ERROR(nn::LinearApply<T>(x.base.trunk, x.bp_mlp, sc.F, &sc.H0));
  // Spatial latent.
  if (c.encoder) {
    sc.Xenc.resize(B, kEncoderGeometryInputs + D);
    for (int64_t r = 0; r < B; ++r) {
      const size_t g = static_cast<size_t>(b + r);
      T* row = sc.Xenc.row(r).data();
      for (int k = 0; k < 3; ++k) row[k] = x.sampler.nm_a[k] * in.means[g * 3 + k] + x.sampler.nm_b[k];
      internal::GeometryInputs(in.opacity_logits[g], in.log_scales + g * 3, in.rotations + g * 4, row + 3);
    }
    sc.Xenc.rightCols(D) = sc.S;
    EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.enc_in, ep, sc.Xenc, &sc.E0));
    const size_t nl = L.enc_linear.size();
    sc.enc_z.resize(nl), sc.enc_n.resize(nl), sc.enc_a.resize(nl), sc.ln_cache.resize(nl), sc.act_cache.resize(nl);
    const Mat<T>* prev = &sc.E0;
    for (size_t i = 0; i < nl; ++i) {
      EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.enc_linear[i], ep, *prev, &sc.enc_z[i]));
      EXT_RETURN_IF_ERROR(nn::LayerNormForward<T>(L.enc_norm[i], ep, sc.enc_z[i], &sc.enc_n[i], &sc.ln_cache[i]));
      nn::ActivationForward<T>(c.activation, sc.enc_n[i], &sc.enc_a[i], &sc.act_cache[i]);
      prev = &sc.enc_a[i];
    }
    sc.q0 = *prev;
  } else {
    sc.q0 = sc.H0;
  }
  if (c.vae) {
    if (c.vae_dilation > 0) {
      // μ from the latent, log σ² from the dilated samples (extended_config.h).
      EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.vae_mu, ep, sc.q0, &sc.mu));
      EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.vae_var, ep, sc.Sdil, &sc.lv));
      sc.ML.resize(B, 2 * L.vae.latent);
      sc.ML << sc.mu, sc.lv;
    } else {
      EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.vae_in, ep, sc.q0, &sc.ML));
    }
    if (pass.training) {
      const int lat = L.vae.latent;
      sc.eps.resize(B, lat);
      for (int64_t r = 0; r < B; ++r)
        for (int i = 0; i < lat; ++i)
          sc.eps(r, i) = static_cast<T>(Normal(pass.noise_seed, static_cast<uint64_t>(b + r), static_cast<uint64_t>(i)));
      EXT_RETURN_IF_ERROR(nn::VaeSampleForward<T>(L.vae, sc.ML, sc.eps, &sc.z, &sc.vae_cache));
    } else {
      EXT_RETURN_IF_ERROR(nn::VaeMean<T>(L.vae, sc.ML, &sc.z));
    }
    T kl = 0;
    EXT_RETURN_IF_ERROR(nn::VaeKl<T>(L.vae, sc.ML, T(1), &kl, nullptr));
    sc.kl += static_cast<double>(kl);
    EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.vae_out, ep, sc.z, &sc.q));
  } else {
    sc.q = sc.q0;
  }
  // Tokens.
  const Mat<T>* tok = nullptr;
  if (c.uses_tokens()) {
    if (c.temporal) {
      sc.times.resize(B, K);
      for (int j = 0; j < K; ++j) sc.times.col(j).setConstant(x.sampler.token_time[j]);
      EXT_RETURN_IF_ERROR(nn::FourierTimeForward<T>(L.fourier, sc.times, sc.Ftok, &sc.Tok, &sc.fourier_cache));
      tok = &sc.Tok;
    } else {
      tok = &sc.Ftok;  // one token: f(x, t)
    }
  }
  sc.r.setZero(B, L.model_dim);
  if (c.attention) {
    EXT_RETURN_IF_ERROR(nn::AttentionForward<T>(L.attention, ep, sc.q, *tok, &sc.attn_out, &sc.attn_cache));
    sc.r += sc.attn_out;
  } else if (c.encoder || c.vae) {
    sc.r += sc.q;
  }
  if (c.gru) {
    EXT_RETURN_IF_ERROR(nn::BiGruForward<T>(L.gru, ep, *tok, &sc.gru_out, &sc.gru_cache));
    sc.r += sc.gru_out;
  }
  if (c.temporal && !c.attention && !c.gru) {
    EXT_RETURN_IF_ERROR(nn::LinearApply<T>(L.readout, ep, *tok, &sc.tmp));
    sc.r += sc.tmp;
  }
  if (L.has_gate) {
    // r = gate ⊙ r_raw (extended_config.h): sc.r keeps r_raw for the backward.
    sc.H = sc.H0 + (sc.r.array().rowwise() * Eigen::Map<const nn::RowVec<T>>(ep + L.gate_offset, L.model_dim).array())
                       .matrix();
  } else {
    sc.H = sc.H0 + sc.r;
  }
  sc.Arelu = sc.H.cwiseMax(T(0));
  // Heads.
  auto head = [&](const nn::LinearSpec& l1, const nn::LinearSpec& l2, const T* params, Mat<T>* hidden, T* dst,
                  int k) -> absl::Status {
    EXT_RETURN_IF_ERROR(nn::LinearApply<T>(l1, params, sc.Arelu, hidden));
    Relu(hidden);
    if (dst) {
      EXT_RETURN_IF_ERROR(nn::LinearApply<T>(l2, params, *hidden, &sc.tmp));
      Eigen::Map<Mat<T>>(dst + b * k, B, k) = sc.tmp;
    }
    return absl::OkStatus();
  };
  const bool all = out == nullptr;  // backward: every hidden layer
  if (all || out->dx) EXT_RETURN_IF_ERROR(head(x.base.pos1, x.base.pos2, x.bp_mlp, &sc.P1, all ? nullptr : out->dx, 3));
  if (all || out->dsh) {
    EXT_RETURN_IF_ERROR(head(x.base.sh1, x.base.sh2, x.bp_mlp, &sc.Sh1, all ? nullptr : out->dsh, kShOutputs));
  }
  if (c.decoder) {
    EXT_RETURN_IF_ERROR(head(L.scale1, L.scale2, ep, &sc.X1, all ? nullptr : out->dscale, kDecoderScaleOutputs));
    EXT_RETURN_IF_ERROR(head(L.rot1, L.rot2, ep, &sc.R1, all ? nullptr : out->drot, kDecoderRotationOutputs));
    EXT_RETURN_IF_ERROR(head(L.op1, L.op2, ep, &sc.O1, all ? nullptr : out->dopacity, kDecoderOpacityOutputs));
  }
  return absl::OkStatus();
}

// Backward of NetForward (run just before on the same chunk): parameter gradients into the
// thread's arrays, dL/dS (encoder) into sc.dX's right columns, dL/d(token features) into sc.dFtok,
// dL/d(geometry) applied to the canonical gradients.
template <typename T>
absl::Status NetBackward(const Ctx<T>& x, const ExtPass& pass, const ExtInputs<T>& in, const ExtOutputGrads<T>& g,
                         T kl_weight, int64_t b, int64_t e, Scratch<T>& sc, const ExtInputGrads<T>& grads) {
  const ExtendedFieldConfig& c = x.c;
  const ExtendedLayout& L = x.L;
  const T* ep = x.m.ext_params;
  T* gb = sc.base_grad.data();
  T* ge = sc.ext_grad.data();
  const int64_t B = e - b;
  const int D = L.feature_dim, K = L.tokens, kc = c.center_token(), M = L.model_dim;
  sc.dA.setZero(B, M);
  auto head = [&](const nn::LinearSpec& l1, const nn::LinearSpec& l2, const T* params, T* grad, const Mat<T>& hidden,
                  Mat<T>* d_hidden, const T* d_out, int k) -> absl::Status {
    if (!d_out) return absl::OkStatus();
    const Eigen::Map<const Mat<T>> dy(d_out + b * k, B, k);
    EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(l2, params, hidden, dy, d_hidden, false, grad));
    ReluMask(hidden, d_hidden);
    return nn::LinearGrad<T>(l1, params, sc.Arelu, *d_hidden, &sc.dA, true, grad);
  };
  EXT_RETURN_IF_ERROR(head(x.base.pos1, x.base.pos2, x.bp_mlp, gb, sc.P1, &sc.dP1, g.d_dx, 3));
  EXT_RETURN_IF_ERROR(head(x.base.sh1, x.base.sh2, x.bp_mlp, gb, sc.Sh1, &sc.dSh1, g.d_dsh, kShOutputs));
  if (c.decoder) {
    EXT_RETURN_IF_ERROR(head(L.scale1, L.scale2, ep, ge, sc.X1, &sc.dX1, g.d_dscale, kDecoderScaleOutputs));
    EXT_RETURN_IF_ERROR(head(L.rot1, L.rot2, ep, ge, sc.R1, &sc.dR1, g.d_drot, kDecoderRotationOutputs));
    EXT_RETURN_IF_ERROR(head(L.op1, L.op2, ep, ge, sc.O1, &sc.dO1, g.d_dopacity, kDecoderOpacityOutputs));
  }
  sc.dH = sc.dA;
  ReluMask(sc.H, &sc.dH);  // dL/dH = dL/dH0
  // dL/dr_raw = gate ⊙ dL/dH; dL/dgate = Σ_rows r_raw ⊙ dL/dH.
  if (L.has_gate) {
    const Eigen::Map<const nn::RowVec<T>> gate(ep + L.gate_offset, M);
    nn::AddColumnSums((sc.r.array() * sc.dH.array()).matrix(), ge + L.gate_offset);
    sc.dr = (sc.dH.array().rowwise() * gate.array()).matrix();
  } else {
    sc.dr = sc.dH;
  }
  const Mat<T>* tok = c.temporal ? &sc.Tok : &sc.Ftok;
  if (c.uses_tokens()) sc.dTok.setZero(B, static_cast<Eigen::Index>(K) * L.token_dim);
  sc.dq.setZero(B, M);
  if (c.temporal && !c.attention && !c.gru) {
    EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.readout, ep, *tok, sc.dr, &sc.dTok, true, ge));
  }
  if (c.gru) {
    EXT_RETURN_IF_ERROR(nn::BiGruBackward<T>(L.gru, ep, sc.gru_cache, sc.dr, &sc.dTok2, ge));
    sc.dTok += sc.dTok2;
  }
  if (c.attention) {
    EXT_RETURN_IF_ERROR(nn::AttentionBackward<T>(L.attention, ep, sc.attn_cache, sc.dr, &sc.dq2, &sc.dTok2, ge));
    sc.dq += sc.dq2;
    sc.dTok += sc.dTok2;
  } else if (c.encoder || c.vae) {
    sc.dq += sc.dr;
  }
  // VAE: dq -> dz -> d(μ, log σ²) (+ KL) -> dq0.
  if (c.vae) {
    EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.vae_out, ep, sc.z, sc.dq, &sc.dz, false, ge));
    if (pass.training) {
      EXT_RETURN_IF_ERROR(nn::VaeSampleBackward<T>(L.vae, sc.vae_cache, sc.dz, &sc.dML));
    } else {
      sc.dML.setZero(B, 2 * L.vae.latent);
      sc.dML.leftCols(L.vae.latent) = sc.dz;
    }
    T kl = 0;
    EXT_RETURN_IF_ERROR(nn::VaeKl<T>(L.vae, sc.ML, kl_weight, &kl, &sc.dML));
    if (c.vae_dilation > 0) {
      const int lat = L.vae.latent;
      EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.vae_mu, ep, sc.q0, sc.dML.leftCols(lat), &sc.dq0, false, ge));
      EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.vae_var, ep, sc.Sdil, sc.dML.rightCols(lat), &sc.dSdil, false, ge));
    } else {
      EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.vae_in, ep, sc.q0, sc.dML, &sc.dq0, false, ge));
    }
  } else {
    sc.dq0 = sc.dq;
  }
  // dL/dH0: the residual path, plus the latent when it is the trunk output.
  if (!c.encoder) sc.dH += sc.dq0;
  EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(x.base.trunk, x.bp_mlp, sc.F, sc.dH, &sc.dF, false, gb));
  // dL/d(token features): through the Fourier tokens, plus the trunk's input at the centre token.
  if (c.temporal) {
    EXT_RETURN_IF_ERROR(nn::FourierTimeBackward<T>(L.fourier, sc.fourier_cache, sc.dTok, nullptr, &sc.dFtok));
  } else if (c.uses_tokens()) {
    sc.dFtok = sc.dTok;
  } else {
    sc.dFtok.setZero(B, static_cast<Eigen::Index>(K) * D);
  }
  sc.dFtok.middleCols(static_cast<Eigen::Index>(kc) * D, D) += sc.dF;
  // Encoder: back to its inputs (geometry -> canonical parameters, spatial features -> sc.dX).
  if (c.encoder) {
    sc.dE = sc.dq0;
    for (size_t i = L.enc_linear.size(); i-- > 0;) {
      EXT_RETURN_IF_ERROR(nn::ActivationBackward<T>(c.activation, sc.act_cache[i], sc.dE, &sc.dN));
      EXT_RETURN_IF_ERROR(nn::LayerNormBackward<T>(L.enc_norm[i], ep, sc.ln_cache[i], sc.dN, &sc.dZ, ge));
      const Mat<T>& prev = i == 0 ? sc.E0 : sc.enc_a[i - 1];
      EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.enc_linear[i], ep, prev, sc.dZ, &sc.dE, false, ge));
    }
    EXT_RETURN_IF_ERROR(nn::LinearGrad<T>(L.enc_in, ep, sc.Xenc, sc.dE, &sc.dX, false, ge));
    for (int64_t r = 0; r < B; ++r) {
      const size_t gi = static_cast<size_t>(b + r);
      const T* dr = sc.dX.row(r).data();
      if (grads.d_means)
        for (int k = 0; k < 3; ++k) grads.d_means[gi * 3 + k] += dr[k] * x.sampler.nm_a[k];
      internal::GeometryInputsBackward(in.opacity_logits[gi], in.log_scales + gi * 3, in.rotations + gi * 4, dr + 3,
                                       grads.d_opacity_logits ? grads.d_opacity_logits + gi : nullptr,
                                       grads.d_log_scales ? grads.d_log_scales + gi * 3 : nullptr,
                                       grads.d_rotations ? grads.d_rotations + gi * 4 : nullptr);
    }
  }
  return absl::OkStatus();
}

template <typename Fn>
void ForChunks(ThreadPool& pool, int64_t n, int64_t chunk, const Fn& fn) {
  pool.ParallelFor(n, chunk, [&](int64_t b, int64_t e, int tid) {
    for (int64_t c = b; c < e; c += chunk) fn(c, std::min(e, c + chunk), tid);
  });
}

template <typename T>
absl::Status CheckModel(const ExtModel<T>& m, const ExtInputs<T>& in) {
  if (!m.base_layout || !m.base_params || !m.config || !m.layout || (m.layout->total() > 0 && !m.ext_params)) {
    return absl::InvalidArgumentError("extended field: incomplete model");
  }
  if (in.n > 0 && !in.means) return absl::InvalidArgumentError("extended field: null means");
  if (in.n > 0 && m.config->encoder && (!in.opacity_logits || !in.log_scales || !in.rotations)) {
    return absl::InvalidArgumentError("extended field: the encoder needs opacities, scales and rotations");
  }
  if (m.layout->feature_dim != m.base_layout->feature_dim() || m.layout->model_dim != m.base_layout->width) {
    return absl::InvalidArgumentError("extended field: the extension's layout does not match the base field");
  }
  return absl::OkStatus();
}

template <typename T>
WorkspaceT<T>& Get(ExtWorkspace::Impl& impl);

}  // namespace

struct ExtWorkspace::Impl {
  WorkspaceT<float> f;
  WorkspaceT<double> d;
};
ExtWorkspace::ExtWorkspace() : impl_(std::make_unique<Impl>()) {}
ExtWorkspace::~ExtWorkspace() = default;

namespace {
template <>
WorkspaceT<float>& Get<float>(ExtWorkspace::Impl& impl) { return impl.f; }
template <>
WorkspaceT<double>& Get<double>(ExtWorkspace::Impl& impl) { return impl.d; }
}  // namespace

absl::StatusOr<ExtendedField> ExtendedField::Create(DeformationField base, const ExtendedFieldConfig& config,
                                                    uint64_t seed) {
  absl::StatusOr<ExtendedLayout> L = ExtendedLayout::Make(base.config(), config);
  if (!L.ok()) return L.status();
  std::vector<float> p;
  InitExtendedParams(config, *L, seed, &p);
  return ExtendedField(std::move(base), config, std::move(*L), std::move(p));
}

absl::StatusOr<ExtendedField> ExtendedField::FromParams(DeformationField base, const ExtendedFieldConfig& config,
                                                        std::vector<float> params) {
  absl::StatusOr<ExtendedLayout> L = ExtendedLayout::Make(base.config(), config);
  if (!L.ok()) return L.status();
  if (params.size() != L->total()) {
    return absl::InvalidArgumentError(absl::StrCat("extended field: ", params.size(), " parameters, the modules (",
                                                   config.ModulesString(), ") need ", L->total()));
  }
  return ExtendedField(std::move(base), config, std::move(*L), std::move(params));
}

ExtModel<float> ModelOf(const ExtendedField& f) {
  ExtModel<float> m;
  m.base_layout = &f.base().layout();
  m.base_params = f.base().params().data();
  m.config = &f.config();
  m.layout = &f.layout();
  m.ext_params = f.params().data();
  m.aabb = f.base().aabb();
  return m;
}

template <typename T>
absl::StatusOr<double> ExtendedForward(const ExtModel<T>& model, const ExtPass& pass, const ExtInputs<T>& in,
                                       const ExtOutputs<T>& out, ThreadPool& pool, ExtWorkspace& ws_outer) {
  EXT_RETURN_IF_ERROR(CheckModel(model, in));
  WorkspaceT<T>& ws = Get<T>(ws_outer.impl());
  const int nt = pool.num_threads();
  ws.Reserve(nt);
  for (int t = 0; t < nt; ++t) ws.threads[t].kl = 0, ws.threads[t].status = absl::OkStatus();
  const Ctx<T> ctx(model, pass);
  ForChunks(pool, static_cast<int64_t>(in.n), kRowsPerChunk, [&](int64_t b, int64_t e, int tid) {
    Scratch<T>& sc = ws.threads[tid];
    if (!sc.status.ok()) return;
    ctx.sampler.Forward(in.means, b, e, &sc.S, &sc.Ftok, sc.taps, sc.tbuf, nullptr, &sc.Sdil);
    sc.status = NetForward(ctx, pass, in, b, e, sc, &out);
  });
  double kl = 0;
  for (int t = 0; t < nt; ++t) {
    EXT_RETURN_IF_ERROR(ws.threads[t].status);
    kl += ws.threads[t].kl;
  }
  return kl;
}

template <typename T>
absl::StatusOr<double> ExtendedBackward(const ExtModel<T>& model, const ExtPass& pass, const ExtInputs<T>& in,
                                        const ExtOutputGrads<T>& d_out, double kl_weight,
                                        const ExtInputGrads<T>& grads, ThreadPool& pool, ExtWorkspace& ws_outer) {
  EXT_RETURN_IF_ERROR(CheckModel(model, in));
  if (!grads.d_base || (!grads.d_ext && model.layout->total() > 0)) {
    return absl::InvalidArgumentError("extended field backward: null parameter gradients");
  }
  WorkspaceT<T>& ws = Get<T>(ws_outer.impl());
  const int nt = pool.num_threads();
  ws.Reserve(nt);
  const FieldLayout& BL = *model.base_layout;
  const size_t base_mlp = BL.total - BL.grid_size;
  for (int t = 0; t < nt; ++t) {
    Scratch<T>& sc = ws.threads[t];
    sc.base_grad.assign(base_mlp, T(0));
    sc.ext_grad.assign(model.layout->total(), T(0));
    sc.kl = 0;
    sc.status = absl::OkStatus();
  }
  const Ctx<T> ctx(model, pass);
  const int slots = ctx.sampler.slots_per_row();
  const int C = BL.channels;
  const size_t n = in.n;
  const size_t block = std::min(kBackwardBlock, std::max<size_t>(n, 1));
  ws.samples.resize(block * slots * C);
  ws.taps.resize(block * slots);
  const internal::SlotStore<T> keep{ws.taps.data(), ws.samples.data(), block, C};
  for (size_t b0 = 0; b0 < n; b0 += block) {
    const size_t bn = std::min(block, n - b0);
    ForChunks(pool, static_cast<int64_t>(bn), kBackwardRowsPerChunk, [&](int64_t lb, int64_t le, int tid) {
      Scratch<T>& sc = ws.threads[tid];
      if (!sc.status.ok()) return;
      const int64_t b = static_cast<int64_t>(b0) + lb, e = static_cast<int64_t>(b0) + le;
      const internal::SlotStore<T> rows = keep.from_row(static_cast<size_t>(lb));
      ctx.sampler.Forward(in.means, b, e, &sc.S, &sc.Ftok, sc.taps, sc.tbuf, &rows, &sc.Sdil);
      sc.status = NetForward(ctx, pass, in, b, e, sc, static_cast<const ExtOutputs<T>*>(nullptr));  // sums the KL
      if (!sc.status.ok()) return;
      sc.status = NetBackward(ctx, pass, in, d_out, static_cast<T>(kl_weight), b, e, sc, grads);
      if (!sc.status.ok()) return;
      const T* dS = model.config->encoder ? sc.dX.data() + kEncoderGeometryInputs : nullptr;
      const int64_t dS_stride = model.config->encoder ? sc.dX.cols() : 0;
      const T* dSdil = model.config->vae && model.config->vae_dilation > 0 ? sc.dSdil.data() : nullptr;
      ctx.sampler.Backward(in.means, b, e, dS, dS_stride, sc.dFtok.data(), rows, grads.d_means, dSdil);
    });
    for (int t = 0; t < nt; ++t) EXT_RETURN_IF_ERROR(ws.threads[t].status);
    ctx.sampler.Scatter(bn, keep, grads.d_base, pool);
  }
  double kl = 0;
  for (int t = 0; t < nt; ++t) {
    const Scratch<T>& sc = ws.threads[t];
    T* ob = grads.d_base + BL.grid_size;
    for (size_t i = 0; i < base_mlp; ++i) ob[i] += sc.base_grad[i];
    for (size_t i = 0; i < sc.ext_grad.size(); ++i) grads.d_ext[i] += sc.ext_grad[i];
    kl += sc.kl;
  }
  return kl;
}

#define EXT_INSTANTIATE(T)                                                                                        \
  template absl::StatusOr<double> ExtendedForward<T>(const ExtModel<T>&, const ExtPass&, const ExtInputs<T>&,      \
                                                     const ExtOutputs<T>&, ThreadPool&, ExtWorkspace&);            \
  template absl::StatusOr<double> ExtendedBackward<T>(const ExtModel<T>&, const ExtPass&, const ExtInputs<T>&,     \
                                                      const ExtOutputGrads<T>&, double, const ExtInputGrads<T>&,   \
                                                      ThreadPool&, ExtWorkspace&);
EXT_INSTANTIATE(float)
EXT_INSTANTIATE(double)

}  // namespace streetsim::field
