// NnKernels' internals shared by its two sources (vk_nn_kernels.cc: scratch, checks, Linear,
// element-wise ops and column sums; vk_nn_kernels_seq.cc: LayerNorm, tokens, VAE, attention, GRU).
#pragma once

#include <cstdint>
#include <initializer_list>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "render/vulkan/field/nn/vk_nn_kernels.h"

namespace streetsim::field::vknn {

inline constexpr uint32_t kWg = 256;   // field_common.glsl: FIELD_WG
inline constexpr uint32_t kTile = 64;  // field_linear*.comp: 64 x 64 tiles; nn_colsum.comp: 64 columns

inline uint32_t DivUp(uint64_t a, uint64_t b) { return static_cast<uint32_t>((a + b - 1) / b); }

// A view's (offset, stride) in a push-constant block (two uints, as the shaders declare them).
struct OffStride {
  uint32_t off = 0, stride = 0;
};
inline OffStride Os(const View& v) { return {v.offset, v.stride}; }

// A view with its name, for the checks' messages.
struct Named {
  const char* name;
  View v;
};

struct NnKernels::Impl {
  const vulkan::Context* ctx = nullptr;
  std::unique_ptr<vulkan::ComputePipeline> linear, linear_grad, reduce, pointwise, colsum, layer_norm, fourier, vae,
      attention, gru;
  // Parameter-gradient partial sums: chunks x (up to max_param_floats) floats.
  vulkan::Buffer partials;
  uint32_t max_rows = 0, max_param_floats = 0, rows_per_chunk = 0;

  // Every view: a buffer, stride >= cols, inside its buffer, every index within 32 bits; else fails
  // `rec` naming `op` and the view, and returns false (nothing is recorded).
  bool CheckViews(vulkan::Recorder& rec, const char* op, std::initializer_list<Named> views) const;
  // Same shape as `want_rows` x `want_cols`.
  bool CheckShape(vulkan::Recorder& rec, const char* op, const Named& v, uint32_t want_rows, uint32_t want_cols) const;
  // [offset, offset + count) of a parameter (or gradient) buffer.
  bool CheckParams(vulkan::Recorder& rec, const char* op, const char* what, const vulkan::Buffer& b, uint64_t offset,
                   uint64_t count) const;
  // The scratch holds `chunks(rows)` x `floats`.
  bool CheckScratch(vulkan::Recorder& rec, const char* op, uint32_t rows, uint64_t floats) const;
  uint32_t Chunks(uint32_t rows) const { return DivUp(rows, rows_per_chunk); }

  // partials[chunk * p_stride + p_off + k] = column sums of a (⊙ b) over each chunk.
  void ColSumPartials(vulkan::Recorder& rec, View a, const View* b, uint32_t p_off, uint32_t p_stride) const;
  // d[dst_off + i] += sum over chunks of partials[src_off + c * src_stride + i], i < count.
  void Reduce(vulkan::Recorder& rec, uint32_t rows, uint32_t count, uint32_t src_off, uint32_t src_stride,
              const vulkan::Buffer& d, uint32_t dst_off) const;
  // nn_pointwise.comp.
  void Pointwise(vulkan::Recorder& rec, uint32_t op, uint32_t act, View a, View b, View c, const vulkan::Buffer* p,
                 uint32_t g_off) const;
};

// The pipelines of vk_nn_kernels_seq.cc's kernels.
absl::Status CreateSeqPipelines(NnKernels::Impl& impl);

// nn_pointwise.comp: OP_*.
inline constexpr uint32_t kOpAct = 0, kOpActGrad = 1, kOpAdd = 2, kOpGate = 3, kOpGateGrad = 4;

}  // namespace streetsim::field::vknn
