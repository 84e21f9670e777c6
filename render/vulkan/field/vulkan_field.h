// The deformation field (docs/field.md, spec section 3) on any Vulkan device: forward (HexPlane
// features, trunk, Δposition and ΔSH heads) and backward (MLP and plane-texel gradients, dL/d
// canonical mean) as compute shaders, with the cpu's formulas (scene/field/field_eval.h) and the
// same flat parameter layout (FieldLayout), so that gradients from either side are
// interchangeable. The cpu double path stays the reference (tests/field/vulkan_field_test.cc).
//
// Host round trip (for now): every call uploads the canonical means (and the output gradients)
// in batches of `batch_rows` Gaussians, runs the batch's kernels in one command buffer, and reads
// the outputs back to host arrays. The parameters stay on the device between calls
// (UpdateParams after an optimiser step re-uploads them); Backward zeroes the device gradient,
// accumulates every batch into it and downloads it once at the end (136 MiB at spec sizes).
//
// Not thread-safe: one caller at a time.
#pragma once

#include <cstddef>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_adam.h"
#include "scene/field/field_config.h"
#include "scene/field/field_eval.h"
#include "scene/field/field_regularizers.h"

namespace streetsim::field {

struct VulkanFieldOptions {
  // kGpu: a discrete / integrated GPU when there is one, else lavapipe (STREETSIM_VK_DEVICE
  // overrides, as for the renderer).
  VulkanDevicePreference device = VulkanDevicePreference::kGpu;
  // Plane-gradient scatter with a compare-and-swap loop even where VK_EXT_shader_atomic_float's
  // add is available (tests both paths on one device).
  bool force_cas_atomics = false;
  // Gaussians per batch (per submit); lowered to what the device's maxStorageBufferRange allows.
  size_t batch_rows = 65536;
  // Largest plane buffer in bytes (0: the device's maxStorageBufferRange). Tests set it small to
  // spread a small field's planes over several buffers, as the spec's 136 MiB are on lavapipe.
  size_t max_plane_buffer_bytes = 0;
};

// Times of the last Forward / Backward.
struct VulkanFieldTimings {
  double device_ms = 0;  // device timestamps around each batch's kernels, summed (0: no timestamps)
  double wall_ms = 0;    // the whole call: uploads, kernels, readbacks, host-side adds
  int batches = 0;
};

class VulkanField {
 public:
  // Uploads `params` (layout.total floats, FieldLayout order). FailedPrecondition when there is
  // no Vulkan device or the device cannot hold the planes; InvalidArgument for bad sizes.
  static absl::StatusOr<std::unique_ptr<VulkanField>> Create(const FieldLayout& layout,
                                                             std::span<const float> params,
                                                             const VulkanFieldOptions& options = {});
  static absl::StatusOr<std::unique_ptr<VulkanField>> Create(const DeformationField& field,
                                                             const VulkanFieldOptions& options = {});
  ~VulkanField();
  VulkanField(const VulkanField&) = delete;
  VulkanField& operator=(const VulkanField&) = delete;

  // Re-uploads every parameter (after an optimiser step); same size as at creation.
  absl::Status UpdateParams(std::span<const float> params);

  // Δposition (*dx, n * 3) and ΔSH (*dsh, n * 48, ΔSH[k][c] at 3k + c; null: not computed) of the
  // Gaussians at `means` (n * 3, world metres), as FieldForward<float>.
  absl::Status Forward(const FieldQuery& query, std::span<const float> means, std::vector<float>* dx,
                       std::vector<float>* dsh);

  // As FieldBackward<float>: given dL/dΔposition (n * 3) and dL/dΔSH (n * 48) (empty = zero),
  // ADDS dL/d(parameters) to d_params (layout.total) and dL/d(means) through the sampling
  // coordinates to d_means (n * 3; empty: not wanted).
  absl::Status Backward(const FieldQuery& query, std::span<const float> means, std::span<const float> d_dx,
                        std::span<const float> d_dsh, std::span<float> d_params, std::span<float> d_means);

  // The optimiser on the device (docs/field.md "The optimiser on the device"): the
  // fine stage keeps the gradient, the plane regularisers and Adam where the field is, so that
  // neither the gradient (136 MiB at spec sizes) nor the parameters cross the bus per iteration;
  // the host reads the parameters back for checkpoints and at the end of a run.
  //
  // As Backward, but the parameter gradient stays on the device (replacing the previous one) for
  // RegularizeAndStep; dL/d(means) is still ADDED to d_means (empty: not wanted).
  absl::Status BackwardOnDevice(const FieldQuery& query, std::span<const float> means, std::span<const float> d_dx,
                                std::span<const float> d_dsh, std::span<float> d_means);
  // Adds the plane regularisers' gradient (PlaneRegularizers' formulas, at the parameters before
  // this step) to the device gradient, then takes one Adam step over every parameter
  // (FieldAdamStep's update; `step` is this step's number, from 1, for the bias corrections).
  // The moments start at 0 unless SetAdamMoments gave them. Returns the regularisers' losses
  // (per-workgroup float sums, added in double).
  absl::StatusOr<RegularizerLosses> RegularizeAndStep(const RegularizerWeights& weights, const FieldLrs& lrs,
                                                      int64_t step);
  // Makes the optimiser's pipelines and buffers (Adam's moments, 2 x the parameters' size, at 0)
  // now rather than at the first RegularizeAndStep, so that a device without room for them can
  // be told apart up front. ResourceExhausted / FailedPrecondition from the device.
  absl::Status PrepareOptimizer();
  // Adam's moments (layout.total floats each, FieldAdamState's order) to and from the device.
  absl::Status SetAdamMoments(std::span<const float> m, std::span<const float> v);
  absl::Status ReadAdamMoments(std::span<float> m, std::span<float> v);
  // The device's parameters (layout.total floats) into `params`.
  absl::Status ReadParams(std::span<float> params);

  const FieldLayout& layout() const;
  std::string device_description() const;
  bool is_cpu_device() const;       // a CPU implementation of Vulkan (lavapipe)
  bool uses_float_atomics() const;  // false: the compare-and-swap scatter
  int plane_buffers() const;        // how many storage buffers hold the planes
  size_t batch_rows() const;        // after the device's limits
  const VulkanFieldTimings& last_forward() const;
  const VulkanFieldTimings& last_backward() const;

  struct Impl;

 private:
  explicit VulkanField(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace streetsim::field
