// Serving the field fast (method.md section 3): a pass over the log's time range finds the
// Gaussians whose deformation does not move, bakes their time-mean deformation into their
// canonical parameters once, and evaluates the field per timestamp for the others only. The
// deformed scene of the last timestamp is kept, so the field runs once per timestamp however many
// cameras and LiDARs render it.
#pragma once

#include <algorithm>
#include <cstdint>
#include <functional>
#include <initializer_list>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

struct StaticSkipOptions {
  int num_samples = 50;              // times spread evenly over the log's range, ends included
  double motion_threshold_m = 0.01;  // static: the Δx box over all samples has a diagonal below this
  // ... and every ΔSH coefficient (of the store's degree) varies by less than this over the samples
  // (SH units; 0.01 is ~0.3 % of full-scale colour through C0).
  double sh_threshold = 0.01;
  // The extended field's decoder heads (extended_serving.h), each Δ's range over the samples:
  // every Δlog-scale component below log_scale_threshold (0.01: the baked scale is within 0.5 %),
  // every Δ of the raw quaternion's components below rotation_threshold (0.01: for a unit
  // quaternion at most ~0.01 rad of rotation), the Δopacity logit below opacity_threshold (0.01:
  // opacity within 0.00125).
  double log_scale_threshold = 0.01;
  double rotation_threshold = 0.01;
  double opacity_threshold = 0.01;
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

// Per Gaussian, the range (max - min) and the mean of each output channel of a deformation over
// the analysis samples (AnalyseStatic; the extended field's analysis, extended_serving.cc).
class DeltaRanges {
 public:
  // Channels of row i: `count` values at data[i * stride ...]; a sample's blocks side by side
  // make up the width.
  struct Block {
    const float* data;
    int stride, count;
  };
  void Reset(size_t rows, int width);
  void Add(std::initializer_list<Block> blocks, ThreadPool& pool);  // one sample of every row
  // One sample of some rows: the blocks' row r is row rows[r], r < n (the mean of a row counts the
  // samples of every Add since Reset: only meaningful for rows present in all of them).
  void Add(std::initializer_list<Block> blocks, const uint32_t* rows, size_t n, ThreadPool& pool);
  float range(size_t row, int k) const { return hi_[row * width_ + k] - lo_[row * width_ + k]; }
  float mean(size_t row, int k) const { return static_cast<float>(sum_[row * width_ + k] / samples_); }
  // max over channels [k0, k0 + count) of range (0 when count is 0).
  double max_range(size_t row, int k0, int count) const;

 private:
  size_t rows_ = 0;
  int width_ = 0, samples_ = 0;
  std::vector<float> lo_, hi_;
  std::vector<double> sum_;
};

// S3Gaussian's test of a static Gaussian: the Δx range box (channels 0-2) has a diagonal below
// motion_threshold_m and each of the next `sh_values` channels (ΔSH) varies by less than sh_threshold.
bool MotionAndColourStatic(const DeltaRanges& r, size_t row, int sh_values, const StaticSkipOptions& o);

// S3Gaussian's field evaluated on a device for ServingField (render/vulkan/field/vulkan_serving.h):
// Δx (*dx, n * 3) and ΔSH (*dsh, n * 48; null: not wanted) of the compact `means` (n * 3) at
// `query`, as FieldForward<float>. `field` is the serving field's own (the device may upload its
// parameters on the first call).
using FieldDeviceForward = std::function<absl::Status(const DeformationField& field, const FieldQuery& query,
                                                      std::span<const float> means, std::vector<float>* dx,
                                                      std::vector<float>* dsh)>;

// `device` (optional): each sample's evaluation through it instead of the cpu (the same rows and
// query; an error of the device is returned, the caller decides whether to retry on the cpu).
absl::StatusOr<StaticAnalysis> AnalyseStatic(const DeformationField& field, const GaussianStore& canonical,
                                             const StaticSkipOptions& options, ThreadPool& pool,
                                             const FieldDeviceForward* device = nullptr);

// A scene deformed at the requested time, evaluated once per time coordinate: what the server
// renders from (ServingField below; the extended field's ExtServingField, extended_serving.h).
class ServedScene {
 public:
  virtual ~ServedScene() = default;
  // The deformed scene at a timestamp (clamped to the log's range: after the log end dynamic
  // content holds its last state). Valid until the next call.
  virtual absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool) = 0;
  // What a LiDAR sweep needs: the scene at `time_us` with its geometry (positions, and the scales,
  // rotations and opacities where the field changes them) at that time; its colours may be another
  // time's. Valid until the next call. The default evaluates everything (At).
  virtual absl::StatusOr<const GaussianStore*> GeometryAt(int64_t time_us, ThreadPool& pool) {
    return At(time_us, pool);
  }
  virtual size_t size() const = 0;
  virtual size_t num_dynamic() const = 0;           // Gaussians evaluated per timestamp
  virtual int64_t field_evaluations() const = 0;    // how often the field ran
  virtual FieldTimeRange time_range() const = 0;    // the log's, which At clamps to
  // Cells of the field's time grid over time_range (its time features are linear within a cell;
  // field::TimeCells), or 1 when it has none.
  virtual int time_cells() const = 0;
  virtual std::vector<uint32_t> dynamic_rows() const = 0;  // the Gaussians At changes
  // What At changes from one time to another (rows and parameters; valid while this scene is), for
  // backends that update only those (Engine::UpdateSceneRows).
  virtual ParamsChange changes() const = 0;
  // Where At evaluates the field: "cpu", or the device of SetDevice (the subclasses'), until that
  // device fails.
  const std::string& device() const { return device_; }

 protected:
  ServedScene() = default;
  ServedScene(const ServedScene&) = default;
  ServedScene& operator=(const ServedScene&) = default;
  // A device evaluation failed (no device, device lost, out of memory): a warning, and the cpu
  // from now on; the caller then evaluates this timestamp on the cpu, so no request fails.
  void DeviceFailed(const absl::Status& why);

  std::string device_ = "cpu";
};

// A served scene written straight into a render engine's copy of it: by the engine's own device
// (the serving form's kernel on a Vulkan engine: render/vulkan/field/vulkan_serving.h
// DeviceWriterFor), so that a new time moves nothing across the bus, or into the cpu engine's
// planes (host_planes_writer.h), so that a new time is one pass over them. The host's
// ServedScene::GeometryAt stays what the LiDAR renders.
class DeviceSceneWriter {
 public:
  virtual ~DeviceSceneWriter() = default;
  // Writes the scene at `time_us` (clamped as At clamps) into `scene`: the engine's copy of the
  // same Gaussians at any earlier time (only what changes over time is written).
  virtual absl::Status WriteAt(int64_t time_us, DeviceScene* scene) = 0;
  virtual std::string device() const = 0;  // where it runs, as ServedScene::device()
};

// Cells of a field's time grid over the log's range: time_resolution - 1 with the full time range,
// half of that with S3Gaussian's [0, 1] mapping (only the upper half of the axis is used).
inline int TimeCells(const FieldConfig& c) {
  const int cells = std::max(1, c.time_resolution - 1);
  return c.full_time_range || cells % 2 != 0 ? cells : cells / 2;
}

class ServingField : public ServedScene {
 public:
  // With `device` (a name and its forward, e.g. vulkan_serving.h's VulkanFieldForward): the static
  // analysis and then every timestamp are evaluated there; if the device fails during the analysis
  // the scene moves to the cpu (DeviceFailed) and the analysis is redone there.
  struct Device {
    std::string name;
    FieldDeviceForward forward;
  };
  static absl::StatusOr<ServingField> Create(DeformationField field, GaussianStore canonical,
                                             const StaticSkipOptions& options, ThreadPool& pool,
                                             const Device* device = nullptr);

  absl::StatusOr<const GaussianStore*> At(int64_t time_us, ThreadPool& pool) override;

  size_t size() const override { return baked_.size(); }
  size_t num_dynamic() const override { return dynamic_rows_.size(); }
  const DeformationField& field() const { return field_; }
  int64_t field_evaluations() const override { return evaluations_; }
  FieldTimeRange time_range() const override { return field_.time_range(); }
  int time_cells() const override { return TimeCells(field_.config()); }
  std::vector<uint32_t> dynamic_rows() const override { return dynamic_rows_; }
  ParamsChange changes() const override {
    ParamsChange c;
    c.rows = dynamic_rows_.data();
    c.num_rows = dynamic_rows_.size();
    c.means = true;
    c.sh_coeffs = canonical_.sh_coeffs();
    return c;
  }

  // Evaluates the dynamic Gaussians with `forward` on `device` from the next At on (the static
  // ones keep their baked values); a failing call falls back to the cpu for good (DeviceFailed).
  // Frees the cpu's spatial-feature cache meanwhile (rebuilt on a fall-back).
  void SetDevice(std::string device, FieldDeviceForward forward);

 private:
  // The cpu's evaluation of the dynamic rows at `coord` into dx_ / dsh_.
  void ForwardOnCpu(double coord, ThreadPool& pool);

  DeformationField field_;
  GaussianStore canonical_;
  GaussianStore baked_;    // static Gaussians with their mean deformation, dynamic ones canonical
  GaussianStore current_;  // the deformed scene of last_coord_
  std::vector<uint32_t> dynamic_rows_;  // in spatial (Morton) order
  std::vector<float> dx_, dsh_;  // compact, per dynamic row
  std::vector<float> spatial_;   // [dynamic rows * feature_dim] or empty (not cached)
  bool cache_spatial_ = false;   // StaticSkipOptions::cache_spatial_features
  FieldDeviceForward device_forward_;  // null: the cpu
  std::vector<float> device_means_;    // [dynamic rows * 3], rows in dynamic_rows_ order (device only)
  double last_coord_ = 0;
  bool have_current_ = false;
  int64_t evaluations_ = 0;
  std::unique_ptr<FieldWorkspace> ws_ = std::make_unique<FieldWorkspace>();
};

}  // namespace streetsim::field
