// The extended deformation field's configuration and parameter layout (issue 5; method.md section 2,
// s3gaussian-spec.md section 14; docs/field.md "Extended field (--field extended)").
//
// The extension sits at the spec's one insertion point, between the HexPlane feature f and the
// heads, as a residual on S3Gaussian's trunk output h0 = trunk(f):
//
//   q  = encoder ? Enc([p, opacity, vec Σ, S(x)]) : h0          spatial latent (model dim = width)
//   q  = vae ? Linear_zq(z), z = μ + σ ⊙ ε (training) | μ, (μ, log σ²) = Linear_vae(q) : q
//        (vae_dilation d > 0: μ = Linear_mu(q), log σ² = Linear_var(S_dil(x)), see below)
//   tokens_j = [Fourier(t_j) (temporal only), f(x, t_j)]        t_j = t + jΔ, j = -k..k (temporal)
//                                                               or the single token f(x, t)
//   r  = attention ? Attn(q, tokens) (residual + LayerNorm inside) : (encoder || vae ? q : 0)
//      + gru ? BiGru(tokens) : 0
//      + (temporal && !attention && !gru) ? Linear(tokens) : 0
//   h  = h0 + gate ⊙ r;   S3Gaussian's Δx, ΔSH heads on h;   decoder: Δscale, Δrotation, Δopacity heads
//
// The gate (a learned per-channel vector, ReZero) starts at 0: the fine stage starts from
// S3Gaussian's field and the modules grow in. Without it the randomly initialised modules (whose
// LayerNorm outputs have unit scale) swamp h0 and the field must first unlearn them
// (docs/field.md "Extended field": measured on the moving-cluster scene).
//
// The VAE's dilated variance branch (method.md section 2 item 2, `vae_dilation` = d texels > 0;
// d = 0 is the single Linear_vae above, bit for bit). Per level l (resolution R_l) and spatial
// plane c in {xy, xz, yz} with coordinates (u, v), in that level's continuous texel units
// px = (p + 1) / 2 · (R_l - 1) (p: the normalised position, as S(x) samples it):
//   A_c(x) = ¼ [s_c(u + d, v) + s_c(u - d, v) + s_c(u, v + d) + s_c(u, v - d)]     [C per level]
// where s_c(a, b) is the plane's bilinear sample at the texel coordinates (a, b) under the same
// Tap rules as S(x) (hexplane_kernels.h: align-corners, border clamp to [0, R_l - 1] applied to
// the shifted coordinate, zero coordinate derivative where it clamps). The centre tap is not in
// the average. Then, like S(x),
//   S_dil(x) = concat_l (A_xy ⊙ A_xz ⊙ A_yz)                                      [D]
//   μ = Linear_mu(q) [L],  log σ² = Linear_var(S_dil(x)) [L],  z = μ + σ ⊙ ε | μ,  KL unchanged.
// Our reading of the paper's "dilated convolution": a fixed (unlearned) 4-tap cross of dilation
// d on each plane, averaged, not a learned kernel; the learned part is Linear_var. The variance
// therefore depends on the neighbourhood's features, the mean on the point's. The cpu sums the
// four taps in the order written (from 0), then multiplies by ¼. `--field-modules vae_dilated`
// sets d = 1 (`all` keeps d = 0); a field with d > 0 is field_ext.bin version 2 (extended_io.h).
//
// The decoder's Δlog-scale is bounded where it is added to the canonical log-scale (session 13):
//   log s = log s_c + B tanh(Δ / B),   B = decoder_max_dlog_scale (0: Δ as it comes, unbounded)
// The head itself stays a Linear (the field's forward and backward, cpu and Vulkan, are unchanged);
// DeformSceneExt / DeformBackwardExt and the serving field apply the bound and its derivative
// 1 - tanh². Unbounded, trained KITTI decoders reached |Δ| of 300-370 (scales of exp(±300):
// zero or infinite in float) on a few thousand Gaussians (docs/field.md "The decoder's Δlog-scale").
// A field with B > 0 is field_ext.bin version 3; older files load with B = 0, as they were trained.
//
// With every module off r = 0: the field is S3Gaussian's exactly (a strict ablation, tested).
// The extension's parameters live in their own flat array (the "network" Adam group); the planes
// and S3Gaussian's trunk and heads stay in the DeformationField's array.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/field/field_config.h"
#include "scene/field/nn/activation.h"
#include "scene/field/nn/attention.h"
#include "scene/field/nn/bi_gru.h"
#include "scene/field/nn/fourier_time.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"
#include "scene/field/nn/nn_layout.h"
#include "scene/field/nn/vae_sampler.h"

namespace streetsim::field {

// Encoder input per Gaussian besides the spatial features: normalised position (3), opacity (1),
// the 6 unique entries of Σ = R S Sᵀ Rᵀ.
inline constexpr int kEncoderGeometryInputs = 10;
inline constexpr int kDecoderScaleOutputs = 3, kDecoderRotationOutputs = 4, kDecoderOpacityOutputs = 1;
inline constexpr float kDefaultDecoderMaxDlogScale = 2.302585093f;  // ln 10

// The decoder's Δlog-scale as added to the canonical log-scale, in place: B tanh(Δ / B) for B > 0,
// Δ unchanged for B = 0 (header comment).
inline void BoundDecoderLogScales(float bound, float* dscale, size_t count) {
  if (bound <= 0) return;
  for (size_t i = 0; i < count; ++i) dscale[i] = bound * std::tanh(dscale[i] / bound);
}
// dL/dΔ from dL/d(log s), in place, given the bounded values: d(B tanh(Δ/B))/dΔ = 1 - (bounded/B)².
inline void BoundDecoderLogScalesBackward(float bound, const float* bounded, float* grad, size_t count) {
  if (bound <= 0) return;
  for (size_t i = 0; i < count; ++i) {
    const float u = bounded[i] / bound;
    grad[i] *= 1.0f - u * u;
  }
}

struct ExtendedFieldConfig {
  // One switch per module (method.md section 2 items 1-6).
  bool encoder = false;    // spatial feature encoder
  bool vae = false;        // sparse variational encoder (+ KL)
  bool temporal = false;   // Fourier time + window of K = 2k+1 plane samples in time
  bool attention = false;  // spatio-temporal multi-head attention (query: the spatial latent)
  bool gru = false;        // bidirectional GRU memory over the tokens
  bool decoder = false;    // extra heads Δscale, Δrotation, Δopacity

  // Sizes (spec 14). The model dim is the base field's width (64): r is added to h0.
  int heads = 4;
  int vae_latent = 32;
  int gru_hidden = 32;
  int window_k = 2;               // K = 2k + 1 tokens with `temporal`
  int fourier_frequencies = 8;    // m
  int encoder_layers = 1;         // L layers of Linear + LayerNorm + activation after the input projection
  // VAE variance branch dilation d in texels (header comment); 0: (μ, log σ²) from one Linear on q.
  int vae_dilation = 0;
  nn::Activation activation = nn::Activation::kRelu;
  // B of the bounded decoder Δlog-scale (header comment; 0 = unbounded, the behaviour before
  // session 13). ln 10: a Gaussian may grow or shrink by up to 10x over time.
  float decoder_max_dlog_scale = kDefaultDecoderMaxDlogScale;
  // Δ, one frame on the field's time axis (time-coordinate units, [-1, 1] spans the log). The
  // trainer sets it from the log's frame interval; tokens t + jΔ clamp to [-1, 1] like t.
  double window_dt = 0.05;

  // Training only (not part of the model): KL weight β (the loss adds β · mean over Gaussians of
  // KL), ramped linearly from 0 over kl_warmup_iterations fine iterations.
  double kl_weight = 1e-4;
  int kl_warmup_iterations = 1000;

  bool any() const { return encoder || vae || temporal || attention || gru || decoder; }
  bool uses_tokens() const { return temporal || attention || gru; }
  int tokens() const { return temporal ? 2 * window_k + 1 : 1; }
  int center_token() const { return temporal ? window_k : 0; }
  absl::Status Validate(const FieldConfig& base) const;

  // "encoder,vae,temporal,attention,gru,decoder" (any subset, comma-separated; "all"; "none").
  static absl::StatusOr<ExtendedFieldConfig> WithModules(const std::string& list);
  std::string ModulesString() const;  // "none" when every module is off
  // Every module on, sizes for a small base field (gradient checks, CLI tests).
  static ExtendedFieldConfig AllOn();
};

// Where the extension's parameters live (nn::NnLayout offsets into its own flat array), and the
// specs of its ops. Built from the base field's config (feature dim, width).
struct ExtendedLayout {
  nn::NnLayout params;
  int feature_dim = 0;   // D = levels * channels
  int model_dim = 0;     // = base width
  int tokens = 1;        // K
  int token_dim = 0;     // 2m + D with temporal, else D
  // Encoder.
  nn::LinearSpec enc_in;
  std::vector<nn::LinearSpec> enc_linear;
  std::vector<nn::LayerNormSpec> enc_norm;
  // VAE.
  nn::LinearSpec vae_in, vae_out;   // vae_in: vae_dilation == 0 only
  nn::LinearSpec vae_mu, vae_var;   // vae_dilation > 0: M -> L on q, D -> L on S_dil(x)
  nn::VaeSpec vae;
  // Tokens and their consumers.
  nn::FourierTimeSpec fourier;
  nn::AttentionSpec attention;
  nn::BiGruSpec gru;
  nn::LinearSpec readout;  // temporal alone: K * token_dim -> M
  bool has_gate = false;   // any module but the decoder: r enters through the gate [M]
  size_t gate_offset = 0;
  // Decoder heads: ReLU -> Linear(M, M) -> ReLU -> Linear(M, k) on h (S3Gaussian's disabled heads).
  nn::LinearSpec scale1, scale2, rot1, rot2, op1, op2;

  size_t total() const { return params.total(); }
  // Forward multiply-adds per Gaussian of the extension alone (excluding plane sampling).
  int64_t Macs(const ExtendedFieldConfig& c) const;

  static absl::StatusOr<ExtendedLayout> Make(const FieldConfig& base, const ExtendedFieldConfig& config);
};

// Forward multiply-adds per Gaussian of S3Gaussian's trunk and heads (for the bench's comparison).
int64_t BaseMlpMacs(const FieldLayout& layout);

// Initial values: Linear Xavier-uniform / PyTorch bias, LayerNorm (1, 0), GRU U(±1/√H); the gate
// and the last Linear of each decoder head are zero so that switching modules on does not move
// the scene at the start of the fine stage.
template <typename T>
void InitExtendedParams(const ExtendedFieldConfig& config, const ExtendedLayout& layout, uint64_t seed,
                        std::vector<T>* params);

}  // namespace streetsim::field
