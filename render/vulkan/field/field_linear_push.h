// Push constants and flags of the GEMM shaders shared by the deformation field (vulkan_field.cc)
// and the extended field's kernels (nn/vk_nn_kernels.cc): shaders/field_linear.comp,
// field_linear_grad.comp, field_reduce.comp. Change both sides together.
#pragma once

#include <cstdint>

namespace streetsim::field::vkgemm {

// field_linear.comp flags.
inline constexpr uint32_t kReluIn = 1, kReluOut = 2, kTrans = 4, kAccum = 8, kMask = 16, kBias = 32;
// field_linear_grad.comp: b_off meaning "no bias column".
inline constexpr uint32_t kNoBias = 0xffffffffu;
inline constexpr uint32_t kTile = 64;  // 64 x 64 output tiles

// Y = X W^T (+ b), or the transposed form; X, Y row-strided views.
struct LinearPush {
  uint32_t rows, K, N, w_off, b_off, flags;
  uint32_t x_off, x_stride, y_off, y_stride;
};
// Per-chunk partial sums of dY^T [X | 1] at w_off / b_off of each chunk's block.
struct GradPush {
  uint32_t rows, N, K, rows_per_chunk, w_off, b_off, partial_stride, relu_in;
  uint32_t dy_off, dy_stride, x_off, x_stride;
};
// d[dst_off + i] += sum over chunks, in order, of partials[src_off + c * src_stride + i].
struct ReducePush {
  uint32_t count, chunks, src_off, src_stride, dst_off;
};

}  // namespace streetsim::field::vkgemm
