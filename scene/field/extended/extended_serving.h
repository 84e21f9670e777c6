// Serving an extended field (docs/field.md "Extended field", "Serving"): the static skip of
// static_skip.h with the extended field's outputs. A pass over the log's time range finds the
// Gaussians none of whose Δs vary (Δx, ΔSH and, with the decoder, Δlog-scale, Δrotation,
// Δopacity: thresholds in StaticSkipOptions), bakes their time-mean Δs into their canonical
// parameters once, and runs ExtendedForward (inference: z = μ) per timestamp on the others only.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

// The canonical inputs of ExtendedForward for some rows of a store, compact (ExtendedForward takes
// contiguous rows).
struct ExtCompactInputs {
  std::vector<float> means, opacity_logits, log_scales, rotations;
  // Row r is g's row offset + rows[r].
  void Gather(const GaussianStore& g, const uint32_t* rows, size_t n, size_t offset = 0);
  ExtInputs<float> view() const {
    return {opacity_logits.size(), means.data(), opacity_logits.data(), log_scales.data(), rotations.data()};
  }
};

// The extended field evaluated on a device for ExtServingField (render/vulkan/field/vulkan_serving.h):
// as ExtendedForward<float> with `field`'s parameters (inference pass: z = μ). `field` is the
// serving field's own (the device may upload its parameters on the first call).
using ExtDeviceForward = std::function<absl::StatusOr<double>(const ExtendedField& field, const ExtPass& pass,
                                                              const ExtInputs<float>& in,
                                                              const ExtOutputs<float>& out)>;

class ExtServingField : public ServedScene {
 public:
  // `canonical` must have SH degree 3. With options.enabled false every Gaussian is evaluated at
  // every timestamp (then At equals ExtDeformedStore up to float rounding: other row batches).
  // With `device` (vulkan_serving.h's VulkanExtFieldForward): the static analysis and then every
  // timestamp are evaluated there; a device failure during the analysis moves the scene to the cpu
  // (DeviceFailed), which finishes the analysis.
  struct Device {
    std::string name;
    ExtDeviceForward forward;
  };
  static absl::StatusOr<std::unique_ptr<ExtServingField>> Create(ExtendedField field, GaussianStore canonical,
                                                                 const StaticSkipOptions& options, ThreadPool& pool,
                                                                 const Device* device = nullptr);

  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool) override;
  size_t size() const override { return baked_.size(); }
  size_t num_dynamic() const override { return rows_.size(); }
  int64_t field_evaluations() const override { return evaluations_; }
  const DeformationField& field() const { return field_.base(); }
  FieldTimeRange time_range() const override { return field_.base().time_range(); }
  int time_cells() const override { return TimeCells(field_.base().config()); }
  std::vector<uint32_t> dynamic_rows() const override { return rows_; }
  ParamsChange changes() const override {  // every parameter the decoder may change
    ParamsChange c;
    c.rows = rows_.data();
    c.num_rows = rows_.size();
    c.means = c.log_scales = c.rotations = c.opacity = true;
    c.sh_coeffs = canonical_.sh_coeffs();
    return c;
  }
  const ExtendedField& extended() const { return field_; }

  // Evaluates the dynamic Gaussians with `forward` on `device` from the next At on (the static
  // ones keep their baked values; an analysis already done stays as it is: pass the device to
  // Create to have it run there too); a failing call falls back to the cpu for good (DeviceFailed).
  void SetDevice(std::string device, ExtDeviceForward forward);

 private:
  explicit ExtServingField(ExtendedField field) : field_(std::move(field)) {}
  absl::Status Analyse(const StaticSkipOptions& o, ThreadPool& pool);
  // One evaluation of the analysis or of At: on the device while it works, else the cpu.
  absl::StatusOr<double> Evaluate(const ExtPass& pass, const ExtInputs<float>& in, const ExtOutputs<float>& out,
                                  ThreadPool& pool);

  ExtendedField field_;
  GaussianStore canonical_;
  GaussianStore baked_;    // static Gaussians with their mean Δs, dynamic ones canonical
  GaussianStore current_;  // the deformed scene of last_coord_
  std::vector<uint32_t> rows_;  // dynamic rows, in spatial (Morton) order
  ExtCompactInputs inputs_;  // the dynamic rows', in rows_ order
  std::vector<float> dx_, dsh_, dscale_, drot_, dopacity_;  // compact outputs
  double last_coord_ = 0;
  bool have_current_ = false;
  int64_t evaluations_ = 0;
  ExtDeviceForward device_forward_;  // null: the cpu
  std::unique_ptr<ExtWorkspace> ws_ = std::make_unique<ExtWorkspace>();
};

}  // namespace streetsim::field
