// Serving the field fast (method.md section 3): a pass over the log's time range finds the
// Gaussians whose deformation does not move, bakes their time-mean deformation into their
// canonical parameters once, and evaluates the field per timestamp for the others only. The
// deformed scene of the last timestamp is kept, so the field runs once per timestamp however many
// cameras and LiDARs render it.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

struct StaticSkipOptions {
  int num_samples = 50;              // times spread evenly over the log's range, ends included
  double motion_threshold_m = 0.01;  // static: the Δx box over all samples has a diagonal below this
  // ... and every ΔSH coefficient (of the store's degree) varies by less than this over the samples
  // (SH units; 0.01 is ~0.3 % of full-scale colour through C0).
  double sh_threshold = 0.01;
  bool enabled = true;               // false: every Gaussian is evaluated every time
  bool spatial_order = true;         // evaluate in Morton order (spatial_order.h); false: row order
  // Keep each dynamic Gaussian's spatial-plane product (field_eval.h SpatialFeatures; 4 x 32
  // floats = 512 B per dynamic Gaussian): a timestamp then samples only the space-time planes.
  bool cache_spatial_features = true;
};

struct StaticAnalysis {
  std::vector<uint32_t> dynamic_rows;  // ascending
  std::vector<float> mean_dx;          // [n*3]   time-mean Δx over the samples
  std::vector<float> mean_dsh;         // [n*K*3] time-mean ΔSH (the store's K coefficients)
  size_t num_static() const { return mean_dx.size() / 3 - dynamic_rows.size(); }
};

absl::StatusOr<StaticAnalysis> AnalyseStatic(const DeformationField& field, const GaussianStore& canonical,
                                             const StaticSkipOptions& options, ThreadPool& pool);

class ServingField {
 public:
  static absl::StatusOr<ServingField> Create(DeformationField field, GaussianStore canonical,
                                             const StaticSkipOptions& options, ThreadPool& pool);

  // The deformed scene at a timestamp (clamped to the log's range: after the log end dynamic
  // content holds its last state). Valid until the next call.
  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool);

  size_t size() const { return baked_.size(); }
  size_t num_dynamic() const { return dynamic_rows_.size(); }
  const DeformationField& field() const { return field_; }
  int64_t field_evaluations() const { return evaluations_; }  // how often the field ran

 private:
  DeformationField field_;
  GaussianStore canonical_;
  GaussianStore baked_;    // static Gaussians with their mean deformation, dynamic ones canonical
  GaussianStore current_;  // the deformed scene of last_coord_
  std::vector<uint32_t> dynamic_rows_;  // in spatial (Morton) order
  std::vector<float> dx_, dsh_;  // compact, per dynamic row
  std::vector<float> spatial_;   // [dynamic rows * feature_dim] or empty (not cached)
  double last_coord_ = 0;
  bool have_current_ = false;
  int64_t evaluations_ = 0;
  std::unique_ptr<FieldWorkspace> ws_ = std::make_unique<FieldWorkspace>();
};

}  // namespace streetsim::field
