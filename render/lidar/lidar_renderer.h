// cpu LiDAR renderer: a range image (beams x columns) of a Gaussian scene from one sensor pose.
//
// Every Gaussian is projected into the sensor's spherical image (column coordinate from azimuth,
// beam coordinate from elevation through the beam table, lidar_model.h) with an EWA-style local
// linearisation: the 2D covariance is J W Sigma W^T J^T with J the Jacobian of (column, beam)
// with respect to the sensor-frame point at the Gaussian's mean. Splats are then binned into
// 16x16 tiles, sorted by range (ties by index) and blended front to back per ray with the camera
// path's 3DGS rules (docs/rendering.md; docs/lidar.md states the differences).
//
// Rolling sweep (lidar_sweep.h): given the sensor pose at the sweep's start and end, each column
// has its own interpolated pose and each Gaussian is projected with the pose of the column it falls
// in (one fixed-point step, docs/lidar.md). A static pose is the special case start == end.
//
// Training: Render with keep_for_backward, then Backward with dL/d(range_sum, alpha,
// intensity_sum) per ray gives dL/d(every Gaussian's parameters and reflectance) (lidar_gradients.h,
// lidar_backward.h).
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/status.h"
#include "render/engine.h"
#include "render/lidar/lidar_gradients.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

class ThreadPool;

struct LidarRenderOptions {
  // Per-Gaussian reflectance in [0, 1] ([N], the store's order); null: 0.5 for every Gaussian.
  const std::vector<float>* reflectance = nullptr;
  // A ray returns when its accumulated alpha >= this threshold (deterministic drop) ...
  float return_alpha_threshold = 0.5f;
  // ... or, when sample_drop is set, with probability alpha, drawn from a hash of (seed, beam,
  // column): the same seed gives the same drops on any thread count.
  bool sample_drop = false;
  uint64_t seed = 0;
  // Point cloud of the returns (LidarRenderOutput::points). Each point is in the frame of its own
  // column's pose (the sensor, or kEgo: the ego through LidarModel::T_ego_from_lidar, at the
  // column's time); in the world it is ColumnPose(sweep, columns, point.column) * xyz.
  bool want_points = false;
  enum class PointFrame { kSensor, kEgo };
  PointFrame point_frame = PointFrame::kSensor;
  int64_t sweep_start_us = 0;                    // per-point times are this + column offset
  // kSimd (production): projection and blend vectorised (lidar_simd.inc, AVX2 or AVX-512 picked
  // at run time). kScalar: one Gaussian / one pixel at a time with libm, the reference kSimd is
  // tested against (equal within float tolerance; docs/lidar.md). kSimdAvx2: the AVX2 build even
  // where AVX-512 is available (tests).
  enum class Kernel { kSimd, kScalar, kSimdAvx2 };
  Kernel kernel = Kernel::kSimd;
  // Keep what LidarRenderer::Backward needs (splats, tile lists, pose columns, the model, the
  // reflectance) until the next Render or Upload.
  bool keep_for_backward = false;
};

struct LidarPoints {
  std::vector<Eigen::Vector3f> xyz;
  std::vector<float> intensity;
  std::vector<int64_t> time_us;
  std::vector<uint16_t> beam;
  std::vector<uint16_t> column;
  size_t size() const { return xyz.size(); }
};

struct LidarRenderOutput {
  int beams = 0;
  int columns = 0;
  // All [beams * columns], row-major (row = beam).
  std::vector<float> range;          // metres: expected range / alpha where the ray returns, else 0
  std::vector<float> intensity;      // sum(reflectance alpha T) / alpha where it returns, else 0
  std::vector<float> alpha;          // 1 - final transmittance (return probability)
  std::vector<float> range_sum;      // sum(range alpha T), not normalised (as the camera's depth)
  std::vector<float> intensity_sum;  // sum(reflectance alpha T), not normalised
  LidarPoints points;                // when LidarRenderOptions::want_points
  size_t num_gaussians = 0;
  size_t num_visible = 0;         // splats after culls (wrap-around copies counted)
  size_t num_tile_instances = 0;  // (splat, tile) pairs
  double projection_ms = 0, sort_ms = 0, blend_ms = 0, total_ms = 0;
};

// out->points from out->range / intensity when options.want_points (else empty): one point per
// return along its pixel's ray, in the sensor (or ego) frame, at its column's time. Shared by the
// cpu and Vulkan renderers.
void FillLidarPoints(const LidarModel& model, const LidarRenderOptions& options, LidarRenderOutput* out);

class LidarRenderer {
 public:
  // num_threads <= 0: STREETSIM_THREADS if set, else the hardware's count (ThreadPool).
  explicit LidarRenderer(int num_threads = 0);
  ~LidarRenderer();

  // Validates the store (InvalidArgument when it fails Validate()) and keeps a structure-of-arrays
  // copy of it for the following sweeps: validation and the copy happen once per scene, not per
  // sweep. On error the previously uploaded scene is dropped.
  absl::Status Upload(const GaussianStore& store);
  // Serving: the uploaded scene with only `change`'s rows and values taken from `store` (the same
  // Gaussians otherwise; SH is not the LiDAR's). InvalidArgument when nothing of this size is
  // uploaded or a changed value is not finite (then the upload is dropped).
  absl::Status UpdateRows(const GaussianStore& store, const ParamsChange& change);
  size_t uploaded_size() const;

  // Renders the uploaded scene. InvalidArgument for an invalid model, a non-finite or non-rigid
  // pose, a reflectance array of the wrong size, or nothing uploaded.
  absl::Status Render(const LidarModel& model, const LidarSweepPose& sweep, const LidarRenderOptions& options,
                      LidarRenderOutput* out);
  // Static pose: Render(model, LidarSweepPose::Static(T_world_from_lidar), ...).
  absl::Status Render(const LidarModel& model, const Eigen::Isometry3d& T_world_from_lidar,
                      const LidarRenderOptions& options, LidarRenderOutput* out);

  // Gradients of the last Render (which must have had keep_for_backward, and no Upload since:
  // FailedPrecondition otherwise) for upstream gradients per ray ([beams * columns] each, null =
  // zero). Float; after a kScalar forward the scalar reference backward, else the vectorised one
  // (lidar_backward.h). deterministic: bit-identical across runs and thread counts (one slot per
  // tile-list entry reduced in list order; slower), else per-thread sums (rounding varies).
  absl::Status Backward(const LidarUpstreamGrads& upstream, LidarGaussianGrads* grads, bool deterministic = false);

  // One-shot: Upload(store) then Render (for repeated sweeps of one scene, upload once instead).
  absl::Status Render(const GaussianStore& store, const LidarModel& model,
                      const Eigen::Isometry3d& T_world_from_lidar, const LidarRenderOptions& options,
                      LidarRenderOutput* out);
  absl::Status Render(const GaussianStore& store, const LidarModel& model, const LidarSweepPose& sweep,
                      const LidarRenderOptions& options, LidarRenderOutput* out);

  // Which build of the vectorised kernels kSimd runs here: "avx512", "avx2" or "generic".
  static const char* SimdIsa();

 private:
  struct Work;
  std::unique_ptr<ThreadPool> pool_;
  std::unique_ptr<Work> work_;
};

// Bins a point cloud (sensor frame) into the model's range image: each point goes to the nearest
// beam by elevation (dropped beyond half a beam spacing past the first/last beam) and the column
// of its azimuth; the nearest point wins a pixel. Points outside [min, max] range are dropped.
// range [beams * columns] (0 = no return); intensity likewise when not null.
void BinPointsToRangeImage(const LidarModel& model, const std::vector<Eigen::Vector3f>& points,
                           const std::vector<float>* reflectance, std::vector<float>* range,
                           std::vector<float>* intensity = nullptr);

}  // namespace streetsim
