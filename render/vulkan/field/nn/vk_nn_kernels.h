// The extended field's building blocks (scene/field/nn/, docs/field.md "Extended field modules")
// as Vulkan compute kernels: the same formulas and the same flat parameter layouts (nn::*Spec
// offsets), so that a parameter or gradient array means the same on either side. The cpu ops stay
// the reference (tests/field/vk_nn_kernels_test.cc holds every kernel against them).
//
// Conventions:
// - tensors are row-major blocks of floats in device buffers (View: element (r, c) at
//   offset + r * stride + c), one row per Gaussian, or per Gaussian and token ([B*T, D]);
// - every Record* call records its dispatches into `rec` and returns; it puts a barrier between
//   its own internal passes, never before its first one or after its last: the caller puts
//   rec.Barrier() between dependent calls;
// - parameter gradients are ADDED to a device buffer with the parameters' layout, in an order
//   that does not depend on scheduling (chunk partials summed in chunk order): the same inputs give
//   the same bits on one device;
// - outputs named "written" are overwritten, "added" accumulated.
// Kernels only: no trainer, no server, no host round trips (the composition uploads and reads).
#pragma once

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "scene/field/nn/activation.h"
#include "scene/field/nn/attention.h"
#include "scene/field/nn/fourier_time.h"
#include "scene/field/nn/gru_cell.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"

namespace streetsim::field::vknn {

// A row-major block of floats in a device buffer.
struct View {
  const vulkan::Buffer* buffer = nullptr;
  uint32_t offset = 0;  // floats from the buffer's start
  uint32_t rows = 0, cols = 0;
  uint32_t stride = 0;  // floats from one row to the next (>= cols)
};
inline View Dense(const vulkan::Buffer& b, uint32_t rows, uint32_t cols, uint32_t offset = 0) {
  return View{&b, offset, rows, cols, cols};
}

class NnKernels {
 public:
  static absl::StatusOr<std::unique_ptr<NnKernels>> Create(const vulkan::Context& ctx);
  ~NnKernels();
  NnKernels(const NnKernels&) = delete;
  NnKernels& operator=(const NnKernels&) = delete;

  // Sizes the kernels' own scratch (the partial sums of the parameter-gradient reductions) for
  // rows up to `max_rows` and blocks of up to `max_param_floats` parameters (a Linear's W and b).
  // Call before recording: a Record* call never reallocates (a recorded command buffer may still
  // reference the old buffer); one that would need more records nothing and fails `rec`.
  absl::Status Reserve(uint32_t max_rows, uint32_t max_param_floats);

  // ---- Linear (nn::LinearSpec; W row-major [out x in] at spec.w_offset of `params`) ----
  // y [B, out] (written, or added with accumulate) = x [B, in] W^T + b.
  void Linear(vulkan::Recorder& rec, const nn::LinearSpec& s, const vulkan::Buffer& params, View x, View y,
              bool accumulate);
  // dx [B, in] (written, or added with accumulate) = dy [B, out] W.
  void LinearInputGrad(vulkan::Recorder& rec, const nn::LinearSpec& s, const vulkan::Buffer& params, View dy,
                       View dx, bool accumulate);
  // d_params[W] += dy^T x, d_params[b] += column sums of dy; fixed order. Uses the kernels'
  // own scratch: records partials, a barrier, the reduction, and a trailing barrier (so that the
  // next call may reuse the scratch).
  void LinearParamGrad(vulkan::Recorder& rec, const nn::LinearSpec& s, View x, View dy,
                       const vulkan::Buffer& d_params);

  // ---- Element-wise and row ops ----
  // y (written) = act(x); y may be x (the caller keeps the pre-activation when it needs it).
  void Activation(vulkan::Recorder& rec, nn::Activation a, View x, View y);
  // dx (written) = dy ⊙ act'(x_pre); dx may be dy.
  void ActivationGrad(vulkan::Recorder& rec, nn::Activation a, View x_pre, View dy, View dx);
  // y += x (same shape).
  void Add(vulkan::Recorder& rec, View x, View y);
  // d_params[offset, offset + cols) += column sums of x (fixed order; scratch and barriers as
  // LinearParamGrad).
  void ColumnSums(vulkan::Recorder& rec, View x, const vulkan::Buffer& d_params, uint32_t offset);

  // LayerNorm (nn::LayerNormSpec): y (written) = g ⊙ xhat + b; xhat [R, dim] and rstd [R, 1]
  // (written) are what the backward needs.
  void LayerNorm(vulkan::Recorder& rec, const nn::LayerNormSpec& s, const vulkan::Buffer& params, View x, View y,
                 View xhat, View rstd);
  // dx (written); gain / bias gradients added to d_params (fixed order).
  void LayerNormGrad(vulkan::Recorder& rec, const nn::LayerNormSpec& s, const vulkan::Buffer& params, View xhat,
                     View rstd, View dy, View dx, const vulkan::Buffer& d_params);

  // ReZero gate (extended_config.h): h (written) = h0 + g ⊙ r, g at `gate_offset` of params.
  void Gate(vulkan::Recorder& rec, const vulkan::Buffer& params, uint32_t gate_offset, View h0, View r, View h);
  // dr (written) = g ⊙ dh; d_params[gate] += column sums of dh ⊙ r (fixed order).
  void GateGrad(vulkan::Recorder& rec, const vulkan::Buffer& params, uint32_t gate_offset, View dh, View r, View dr,
                const vulkan::Buffer& d_params);

  // ---- Temporal tokens (nn::FourierTimeSpec) ----
  // tokens [B, T*(2m+F)] (written) from times [B, T] and features [B, T*F].
  void FourierTokens(vulkan::Recorder& rec, const nn::FourierTimeSpec& s, View times, View features, View tokens);
  // d_features [B, T*F] (written) from d_tokens (the time columns carry no parameter).
  void FourierTokensGrad(vulkan::Recorder& rec, const nn::FourierTimeSpec& s, View d_tokens, View d_features);

  // ---- VAE (nn::VaeSpec: latent L) ----
  // z [B, L] (written) = mu + exp(logvar / 2) ⊙ eps, or mu when eps.buffer is null (inference);
  // kl [B, 1] (written) = per-row KL (nn::VaeKl's formula, weight 1).
  void VaeSample(vulkan::Recorder& rec, int latent, View mu_logvar, View eps, View z, View kl);
  // d_mu_logvar [B, 2L] (written) = the sampling's backward of dz plus kl_weight · dKL/d(mu, logvar).
  void VaeSampleGrad(vulkan::Recorder& rec, int latent, View mu_logvar, View eps, View dz, float kl_weight,
                     View d_mu_logvar);

  // ---- Attention core (nn::AttentionSpec's formulas between the projections) ----
  // Q [B, M], K and V [B*T, M] (row b*T + j) -> A [B, H*T] softmax weights, O [B, M] (written).
  void AttentionCore(vulkan::Recorder& rec, int tokens, int heads, int head_dim, View Q, View K, View V, View A,
                     View O);
  // dO [B, M] -> dQ [B, M], dK, dV [B*T, M] (written).
  void AttentionCoreGrad(vulkan::Recorder& rec, int tokens, int heads, int head_dim, View Q, View K, View V, View A,
                         View dO, View dQ, View dK, View dV);

  // ---- GRU step (nn::GruCellSpec, PyTorch's gate order r, z, n) ----
  // gi [B, 3H] = x W_ih^T + b_ih, gh [B, 3H] = h_prev W_hh^T + b_hh (both from Linear), h_prev
  // [B, H] -> h [B, H] (written) and rzn [B, 3H] (written: r, z, n, for the backward).
  void GruStep(vulkan::Recorder& rec, int hidden, View gi, View gh, View h_prev, View h, View rzn);
  // dh [B, H] -> dgi [B, 3H], dgh [B, 3H] (written), dh_prev [B, H] (written: z ⊙ dh; the caller
  // adds dgh W_hh with LinearInputGrad(accumulate)).
  void GruStepGrad(vulkan::Recorder& rec, int hidden, View gh, View rzn, View h_prev, View dh, View dgi, View dgh,
                   View dh_prev);

  struct Impl;

 private:
  explicit NnKernels(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace streetsim::field::vknn
