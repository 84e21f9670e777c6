// The serving form of a field (docs/field.md "Serving form"): what `streetsim serve` evaluates per
// timestamp instead of the field's network. Each moving Gaussian's time-varying parameters
// (position, DC colour, SH bands 1-3 and, for the extended field, log-scale, rotation and opacity:
// whichever the field changes) are fitted over the log's time range by a uniform spline
// (piecewise linear by default, knots on the field's time grid), least squares on samples of the
// exact field; the control points are stored compactly (serving_form_tables.h: position as a line
// plus an int8 residual, the appearance as its time-mean plus a rank-1 change over time).
// Gaussians that do not move keep one value. Evaluating a timestamp is then a 2-tap blend (4 for
// the cubic) per moving Gaussian and a few multiply-adds per channel: memory-bound, no network.
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
#include "scene/field/serving_form_tables.h"
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
  // Rank of the appearance's change over time (serving_form_tables.h), 1..kMaxAppearanceRank.
  int appearance_rank = kDefaultAppearanceRank;
  absl::Status Validate() const;
};

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
                                                          int samples_per_segment, ThreadPool& pool,
                                                          int appearance_rank = kDefaultAppearanceRank);

  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool) override;
  // Only the groups that are not the appearance (a tenth of the work for S3Gaussian's field); a
  // later At of the same time completes the appearance without counting a new evaluation.
  absl::StatusOr<const GaussianStore*> GeometryAt(int64_t time_us, ThreadPool& pool) override;
  // The form at `time_us` into an engine's planes of these Gaussians (Engine::WritablePlanes),
  // every modelled channel of the moving rows, and in the same pass the current store's geometry
  // (as GeometryAt: a GeometryAt of the same time is then free, and this counts as its
  // evaluation). InvalidArgument for planes of another size or SH degree; Internal when a value
  // came out non-finite (the planes' moving rows are then unspecified).
  absl::Status WritePlanesAt(int64_t time_us, const ScenePlanes& planes, ThreadPool& pool);
  size_t size() const override { return current_.size(); }
  size_t num_dynamic() const override { return rows_.size(); }
  int64_t field_evaluations() const override { return evaluations_; }
  FieldTimeRange time_range() const override { return time_range_; }
  int time_cells() const override { return segments(); }
  std::vector<uint32_t> dynamic_rows() const override { return rows_; }
  ParamsChange changes() const override;

  int control_points() const { return control_points_; }
  int degree() const { return degree_; }
  // Where a time falls on the spline: its first control point k, the weights of the `taps`
  // control points from k (w[taps..] are 0) and where they fall on the line between the end
  // points (FormTables' position), as At evaluates it; the ends clamp.
  struct Spline {
    int k = 0, taps = 2;
    float w[4] = {};
    float line = 0;
  };
  struct SplineAxis {
    FieldTimeRange time_range;
    int degree = 1, control_points = 2;
    double Tau(int64_t time_us) const;  // [0, 1] over the time range
    Spline At(int64_t time_us) const { return AtTau(Tau(time_us)); }
    Spline AtTau(double tau) const;
  };
  SplineAxis spline_axis() const { return {time_range_, degree_, control_points_}; }
  const FormTables& tables() const { return tables_; }
  const std::vector<uint32_t>& moving_rows() const { return rows_; }
  int segments() const { return control_points_ - degree_; }
  bool models(FormGroup g) const { return groups_ & (1u << static_cast<int>(g)); }
  const ServingFormError& error() const { return error_; }
  // Per moving Gaussian (dynamic_rows order): its largest position error at the check samples (m).
  // Only after Build (a form read from a cache has its summary, error(), not this).
  const std::vector<float>& position_error_m() const { return position_error_m_; }
  // Frees position_error_m() (4 B per moving Gaussian), so that a form served after its build
  // holds what one read from its cache holds.
  void ForgetPositionErrors() { std::vector<float>().swap(position_error_m_); }
  // Host bytes of the per-Gaussian tables beyond the Gaussians themselves.
  size_t table_bytes() const { return rows_.size() * sizeof(uint32_t) + tables_.bytes(); }
  int appearance_rank() const { return tables_.appearance_rank(); }

 private:
  friend class ServingFormCodec;  // serving_form_io.cc
  ServingForm() = default;
  int modelled_channels() const;  // channels of every modelled group but position
  // Writes the form at tau into `out` (only the moving rows' modelled channels).
  void EvaluateInto(double tau, GaussianStore* out, ThreadPool& pool, uint32_t groups = ~0u) const;
  double Tau(int64_t time_us) const { return spline_axis().Tau(time_us); }
  // Fit's last step: the form against `exact` halfway between the fit samples (error_,
  // position_error_m_).
  absl::Status Check(ServedScene& exact, const std::vector<int64_t>& fit_us, ThreadPool& pool);

  FieldTimeRange time_range_;
  int control_points_ = 0;
  int degree_ = 3;
  uint32_t groups_ = 0;          // bit per FormGroup
  GaussianStore current_;        // the Gaussians at last_tau_ (time-invariant values already in place)
  std::vector<uint32_t> rows_;   // moving Gaussians, ascending
  FormTables tables_;            // the moving Gaussians' control points, row r for rows_[r]
  ServingFormError error_;
  std::vector<float> position_error_m_;
  double last_tau_ = -1;           // current_ holds every modelled group at this time
  double geometry_tau_ = -1;       // current_ holds the groups GeometryAt evaluates at this time
  int64_t evaluations_ = 0;
};

}  // namespace streetsim::field
