// The extended deformation field (scene/field/extended/, docs/field.md "Extended field") on any
// Vulkan device: ExtendedForward<float> / ExtendedBackward<float> with the same semantics, the same
// flat parameter layouts (FieldLayout for the planes and S3Gaussian's MLP, ExtendedLayout for the
// extension) and the same ε, so that outputs and gradients from either side are interchangeable.
// The cpu double path stays the reference (tests/field/vk_ext_field_test.cc).
//
// What runs where: the token sampling and its backward (vk_token_sampler.h, shaders/ext_*), every
// Linear / LayerNorm / activation / gate / Fourier token / VAE / attention / GRU op and its
// backward (render/vulkan/field/nn, NnKernels) on the device; on the host, per batch: ε (drawn with
// the cpu's ext_noise.h and uploaded: exact), the encoder's 10 geometry inputs and their backward
// (encoder_geometry.h: ~100 flops per Gaussian on data the host holds anyway; the device would
// need the canonical opacities / scales / rotations uploaded for them), the Σ KL (rows read back,
// summed in double).
//
// Host round trip per batch of `batch_rows` Gaussians, as VulkanField: inputs up through a mapped
// staging buffer, the batch's kernels in one command buffer, outputs (and KL rows, dL/d(means),
// the encoder's dL/d(geometry)) read back. Parameters stay on the device between calls
// (UpdateParams after an optimiser step re-uploads them); Backward zeroes the device parameter
// gradients, accumulates every batch and downloads them once, ADDED into the caller's arrays.
// Plane gradients come from float atomics (order varies: not bit-reproducible, as VulkanField);
// everything else is in a fixed order.
//
// Not thread-safe: one caller at a time.
#pragma once

#include <cstddef>
#include <memory>
#include <span>
#include <string>

#include "absl/status/statusor.h"
#include "scene/field/extended/extended_field.h"
#include "render/vulkan/field/vulkan_field.h"

namespace streetsim::field {

class VulkanExtendedField {
 public:
  // Uploads the model's parameters (model.base_params: base_layout->total floats; model.ext_params:
  // layout->total()). FailedPrecondition without a Vulkan device, with more than 9 tokens, or when
  // the device cannot hold the planes; InvalidArgument for a malformed model.
  static absl::StatusOr<std::unique_ptr<VulkanExtendedField>> Create(const ExtModel<float>& model,
                                                                     const VulkanFieldOptions& options = {});
  static absl::StatusOr<std::unique_ptr<VulkanExtendedField>> Create(const ExtendedField& field,
                                                                     const VulkanFieldOptions& options = {});
  ~VulkanExtendedField();
  VulkanExtendedField(const VulkanExtendedField&) = delete;
  VulkanExtendedField& operator=(const VulkanExtendedField&) = delete;

  // Re-uploads every parameter (after an optimiser step); same sizes as at creation.
  absl::Status UpdateParams(std::span<const float> base_params, std::span<const float> ext_params);

  // As ExtendedForward<float>: outputs [n * k] (null: not wanted); returns Σ KL (0 without the VAE).
  absl::StatusOr<double> Forward(const ExtPass& pass, const ExtInputs<float>& in, const ExtOutputs<float>& out);

  // As ExtendedBackward<float>: gradients ADDED to grads (d_base, d_ext required; the rest may be
  // null); returns Σ KL.
  absl::StatusOr<double> Backward(const ExtPass& pass, const ExtInputs<float>& in, const ExtOutputGrads<float>& d_out,
                                  double kl_weight, const ExtInputGrads<float>& grads);

  std::string device_description() const;
  bool is_cpu_device() const;  // a CPU implementation of Vulkan (lavapipe)
  bool uses_float_atomics() const;
  int plane_buffers() const;
  size_t batch_rows() const;  // after the device's limits
  const VulkanFieldTimings& last_forward() const;
  const VulkanFieldTimings& last_backward() const;

  struct Impl;

 private:
  explicit VulkanExtendedField(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace streetsim::field
