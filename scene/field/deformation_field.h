// S3Gaussian's spatio-temporal deformation field (spec section 3; docs/field.md): configuration,
// the flat float parameters, the AABB that normalises positions and the log's time range that
// normalises time. The passes are in field_eval.h, the trainer glue in deformed_scene.h.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/field/field_config.h"
#include "scene/field/field_eval.h"

namespace streetsim::field {

struct FieldAabb {
  double min[3] = {-1, -1, -1};
  double max[3] = {1, 1, 1};
};

// The log's time range; the field's time axis spans it.
struct FieldTimeRange {
  int64_t start_us = 0;
  int64_t end_us = 0;
};

class DeformationField {
 public:
  // Spec init (3.1, 3.2): spatial planes U(lo, hi), time planes 1, Linear weights Xavier-uniform,
  // biases U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (PyTorch's default, which S3Gaussian keeps).
  // The AABB must have positive extent on every axis; end_us >= start_us.
  static absl::StatusOr<DeformationField> Create(const FieldConfig& config, const FieldAabb& aabb,
                                                 const FieldTimeRange& time_range, uint64_t seed);
  // Wraps existing parameters (deserialisation); checks sizes.
  static absl::StatusOr<DeformationField> FromParams(const FieldConfig& config, const FieldAabb& aabb,
                                                     const FieldTimeRange& time_range, std::vector<float> params);

  const FieldConfig& config() const { return config_; }
  const FieldLayout& layout() const { return layout_; }
  const FieldAabb& aabb() const { return aabb_; }
  const FieldTimeRange& time_range() const { return time_range_; }
  const std::vector<float>& params() const { return params_; }
  std::vector<float>& mutable_params() { return params_; }

  // Normalised time of a timestamp: tau = (time_us - start) / (end - start) clamped to [0, 1]
  // (before the log start / after its end the field holds its first / last state), then
  // 2 tau - 1 (full_time_range, streetsim's default) or tau (S3Gaussian).
  double NormalisedTime(double tau) const { return config_.full_time_range ? 2 * tau - 1 : tau; }
  double TimeCoordinate(int64_t time_us) const;
  FieldQuery Query(int64_t time_us) const { return QueryAtCoordinate(TimeCoordinate(time_us)); }
  FieldQuery QueryAtCoordinate(double time_coord) const;

 private:
  FieldConfig config_;
  FieldLayout layout_;
  FieldAabb aabb_;
  FieldTimeRange time_range_;
  std::vector<float> params_;
};

absl::Status ValidateAabb(const FieldAabb& aabb);

// The spec's initial values into a flat array of the layout (float or double).
template <typename T>
void InitFieldParams(const FieldConfig& config, const FieldLayout& layout, uint64_t seed, std::vector<T>* params);

}  // namespace streetsim::field
