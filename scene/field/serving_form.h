// The serving form of a field (docs/field.md "Serving form"): what `streetsim serve` evaluates per
// timestamp instead of the field's network. Each moving Gaussian's time-varying parameters
// (position, DC colour, SH bands 1-3 and, for the extended field, log-scale, rotation and opacity:
// whichever the field changes) are fitted over the log's time range by a uniform spline
// (piecewise linear by default, knots on the field's time grid), least squares on samples of the
// exact field; the coefficients are stored quantised (position int16, the rest int8, each with
// its own offset and step per Gaussian and channel). Gaussians that do not move keep one value.
// Evaluating a timestamp is then a 2-tap blend (4 for the cubic) per channel of the moving
// Gaussians: memory-bound, no network.
//
// Build() measures what the form costs: after the fit it compares the form with the exact field at
// the midpoints between the fit samples and records each moving Gaussian's largest position error
// (position_error_m) and the largest error per channel group (ServingFormError).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

struct ServingFormOptions {
  // 1: piecewise linear; 3: uniform cubic B-spline.
  int degree = 1;
  // Spline segments per cell of the exact field's time grid (ServedScene::time_cells; the knots
  // fall on the grid's nodes, where the field's time features have their kinks) in the first fit.
  int segments_per_cell = 1;
  // Fit samples per segment (the exact field is evaluated segments * samples_per_segment + 1 times
  // for the fit, as often again for the error check).
  int samples_per_segment = 4;
  // When the check finds the 99th percentile of the moving Gaussians' position error above this,
  // the fit is redone with twice the segments per cell, up to max_segments_per_cell; a form still
  // above it is not served (train::LoadServedScene). On the trained KITTI scene of docs/field.md
  // "Serving form" one segment per cell leaves a p99 of 86 mm (mostly Gaussians that jitter from
  // one frame to the next) for -0.03 dB of held-out PSNR, and two segments (33 mm) change nothing
  // measurable: the bound is a guard against fields the form cannot follow at all.
  double max_position_error_m = 0.1;
  int max_segments_per_cell = 2;
  absl::Status Validate() const;
};

// The channel groups a form can model, in table order.
// kColour is the DC term, kShBands the SH bands 1-3 (S3Gaussian's field changes all of them, and on
// a trained KITTI scene their change over time is worth 1.2 dB of held-out PSNR).
enum class FormGroup : uint8_t {
  kPosition = 0,
  kColour = 1,
  kLogScale = 2,
  kRotation = 3,
  kOpacity = 4,
  kShBands = 5
};
inline constexpr int kFormGroups = 6;
inline constexpr int kFormGroupChannels[kFormGroups] = {3, 3, 3, 4, 1, 45};

// The largest difference between the form and the exact field over the check samples, per group,
// modelled or not (position in metres, the others in their raw units: SH, log-scale, quaternion
// component, logit).
struct ServingFormError {
  std::array<float, kFormGroups> max{};
  float position_p99_m = 0;  // 99th percentile over moving Gaussians of their largest position error
  int check_samples = 0;
};

class ServingForm : public ServedScene {
 public:
  // Samples `exact` over its time range (At, 2 * segments * samples_per_segment + 1 times) and fits
  // its moving Gaussians. `exact` is left at an arbitrary time.
  static absl::StatusOr<std::unique_ptr<ServingForm>> Build(ServedScene& exact, const ServingFormOptions& options,
                                                            ThreadPool& pool);
  // One fit with `segments` uniform segments of `degree` (1 or 3) over the time range (Build's step).
  static absl::StatusOr<std::unique_ptr<ServingForm>> Fit(ServedScene& exact, int degree, int segments,
                                                          int samples_per_segment, ThreadPool& pool);

  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool) override;
  size_t size() const override { return current_.size(); }
  size_t num_dynamic() const override { return rows_.size(); }
  int64_t field_evaluations() const override { return evaluations_; }
  FieldTimeRange time_range() const override { return time_range_; }
  int time_cells() const override { return segments(); }
  std::vector<uint32_t> dynamic_rows() const override { return rows_; }
  ParamsChange changes() const override;

  int control_points() const { return control_points_; }
  int degree() const { return degree_; }
  int segments() const { return control_points_ - degree_; }
  bool models(FormGroup g) const { return groups_ & (1u << static_cast<int>(g)); }
  const ServingFormError& error() const { return error_; }
  // Per moving Gaussian (dynamic_rows order): its largest position error at the check samples (m).
  // Only after Build (a form read from a cache has its summary, error(), not this).
  const std::vector<float>& position_error_m() const { return position_error_m_; }
  // Host bytes of the per-Gaussian tables beyond the Gaussians themselves.
  size_t table_bytes() const;

 private:
  friend class ServingFormCodec;  // serving_form_io.cc
  ServingForm() = default;
  int modelled_channels() const;  // channels of every modelled group but position
  // Spline weights at normalised time tau in [0, 1]: the first control point and degree_ + 1
  // weights (the rest of w is 0).
  int Weights(double tau, float w[4]) const;
  template <int kTaps>
  void EvaluateTaps(double tau, GaussianStore* out, ThreadPool& pool) const;
  // Writes the form at tau into `out` (only the moving rows' modelled channels).
  void EvaluateInto(double tau, GaussianStore* out, ThreadPool& pool) const;
  double Tau(int64_t time_us) const;
  // Fit's steps: the least-squares coefficients [rows][control points][channels] into the quantised
  // tables (and, when the SH bands do not change, rest_mean [rows][45] into current_); then the
  // form against `exact` halfway between the fit samples (error_, position_error_m_).
  void Quantise(const std::vector<float>& coef, const float* rest_mean, ThreadPool& pool);
  absl::Status Check(ServedScene& exact, const std::vector<int64_t>& fit_us, ThreadPool& pool);

  FieldTimeRange time_range_;
  int control_points_ = 0;
  int degree_ = 3;
  uint32_t groups_ = 0;          // bit per FormGroup
  GaussianStore current_;        // the Gaussians at last_tau_ (time-invariant values already in place)
  std::vector<uint32_t> rows_;   // moving Gaussians, ascending
  // Per moving Gaussian and channel (position first, then the other modelled groups in order):
  // value = offset + step * sum_j w_j q_j.
  std::vector<float> offset_, step_;
  std::vector<int16_t> q_position_;  // [rows][control_points][3]
  std::vector<int8_t> q_other_;      // [rows][control_points][modelled_channels]
  ServingFormError error_;
  std::vector<float> position_error_m_;
  double last_tau_ = -1;
  int64_t evaluations_ = 0;
};

}  // namespace streetsim::field
