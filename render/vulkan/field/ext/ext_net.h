// The extended field's network on Vulkan (internal to VulkanExtendedField): every per-batch device
// buffer the configuration needs, and the recording of the forward (features -> heads) and the
// backward (output gradients -> parameter gradients, dL/dS, dL/d(token features)) as NnKernels
// calls in extended_field.cc's NetForward / NetBackward order. Records only; the caller uploads,
// submits and reads back.
#pragma once

#include <cstdint>
#include <map>
#include <string>

#include "absl/status/status.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "scene/field/extended/extended_config.h"
#include "scene/field/field_config.h"
#include "render/vulkan/field/nn/vk_nn_kernels.h"

namespace streetsim::field::vkext {

// Output columns of the `out` / `gout` buffers: output o is a dense [rows x kOutCols[o]] block at
// float offset batch * kOutCol0[o] (dx, dsh, dscale, drot, dopacity).
inline constexpr int kOutputs = 5;
inline constexpr uint32_t kOutCols[kOutputs] = {3, 48, 3, 4, 1};
inline constexpr uint32_t kOutCol0[kOutputs] = {0, 3, 51, 54, 58};
inline constexpr uint32_t kOutTotal = 59;

class ExtNet {
 public:
  ExtNet(const vulkan::Context& ctx, vknn::NnKernels& nn, const FieldLayout& base, const ExtendedFieldConfig& config,
         const ExtendedLayout& layout)
      : ctx_(ctx), nn_(nn), BL_(base), c_(config), L_(layout) {}

  // Floats per Gaussian of the widest per-row buffer (batch sizing), and the largest parameter
  // block of a Linear / LayerNorm / gate (NnKernels::Reserve).
  uint32_t WidestRow() const;
  uint32_t MaxParamFloats() const;
  // Every buffer for batches of up to `batch` rows (forward and backward).
  absl::Status Allocate(uint32_t batch);
  const vulkan::Buffer& buf(const std::string& name) const { return bufs_.at(name); }

  // Forward of `rows` Gaussians whose token features (ftok), encoder input row (xenc, with the
  // geometry columns) and host inputs (eps, times) are on the device. wanted[o]: output o to `out`.
  // All hidden layers are kept for RecordBackward (which must follow in the same command buffer).
  void RecordForward(vulkan::Recorder& rec, uint32_t rows, bool training, const bool wanted[kOutputs]) const;
  // Backward given gout (present[o]: output o has a gradient): parameter gradients added to
  // d_mlp / d_ext, dL/d(token features) to dftok, dL/d(encoder input) to dxenc.
  void RecordBackward(vulkan::Recorder& rec, uint32_t rows, bool training, float kl_weight,
                      const bool present[kOutputs], const vulkan::Buffer& mlp, const vulkan::Buffer& ext,
                      const vulkan::Buffer& d_mlp, const vulkan::Buffer& d_ext) const;
  // Binds the parameter buffers used by RecordForward (the base MLP from the grid's end on, the
  // extension) before recording.
  void SetParams(const vulkan::Buffer* mlp, const vulkan::Buffer* ext) {
    mlp_ = mlp;
    ext_ = ext;
  }
  // Which buffer holds dL/d(token features) after RecordBackward.
  const vulkan::Buffer& dftok() const;
  // The VAE variance branch's input S_dil and its gradient (null without a dilation).
  bool dilated() const { return c_.vae && c_.vae_dilation > 0; }
  const vulkan::Buffer* sdil() const { return dilated() ? &bufs_.at("sdil") : nullptr; }
  const vulkan::Buffer* dsdil() const { return dilated() ? &bufs_.at("dsdil") : nullptr; }
  uint32_t batch() const { return batch_; }

 private:
  vknn::View V(const std::string& name, uint32_t rows, uint32_t cols, uint32_t offset = 0, uint32_t stride = 0) const;
  // The spatial latent q0, the VAE's output q, the token matrix [rows, K * token_dim].
  vknn::View Q0(uint32_t rows) const;
  vknn::View Q(uint32_t rows) const;
  vknn::View Tok(uint32_t rows) const;
  vknn::View TokRows(const std::string& name, uint32_t rows) const;  // as [rows * K, token_dim]
  vknn::View H(uint32_t rows) const;  // h = h0 + gate ⊙ r (h0 without a gate)
  // Index helpers of the GRU's per-step buffers.
  vknn::View Hidden(bool rev, int step, uint32_t rows) const;  // h after step `step` (-1: zeros)
  void Lin(vulkan::Recorder& rec, const nn::LinearSpec& s, const vulkan::Buffer& p, vknn::View x, vknn::View y,
           bool acc) const {
    nn_.Linear(rec, s, p, x, y, acc);
  }
  void Grad(vulkan::Recorder& rec, const nn::LinearSpec& s, const vulkan::Buffer& p, const vulkan::Buffer& dp,
            vknn::View x, vknn::View dy, vknn::View dx, bool acc) const;

  void RecordAttentionBackward(vulkan::Recorder& rec, uint32_t rows, vknn::View dr, const vulkan::Buffer& ext,
                               const vulkan::Buffer& d_ext) const;
  void RecordGruBackward(vulkan::Recorder& rec, uint32_t rows, vknn::View dr, const vulkan::Buffer& ext,
                         const vulkan::Buffer& d_ext) const;

  const vulkan::Context& ctx_;
  vknn::NnKernels& nn_;
  const FieldLayout& BL_;
  const ExtendedFieldConfig& c_;
  const ExtendedLayout& L_;
  nn::LinearSpec trunk_, pos1_, pos2_, sh1_, sh2_;  // over the base MLP buffer (offsets from grid_size)
  nn::LinearSpec gru_ih_[2], gru_hh_[2];            // fwd, rev
  const vulkan::Buffer* mlp_ = nullptr;
  const vulkan::Buffer* ext_ = nullptr;
  std::map<std::string, vulkan::Buffer> bufs_;
  uint32_t batch_ = 0;
};

}  // namespace streetsim::field::vkext
