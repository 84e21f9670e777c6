// LiDAR evaluation of a scene against a log's real scans (`streetsim eval`, docs/lidar.md
// "Evaluation and serving"): per frame, the scene's sweep is rendered from the log's LiDAR pose
// (T_world_from_ego * T_ego_from_lidar, the log's mounting copied into the model) and compared with
// the real scan binned into the same range image (BinPointsToRangeImage).
//
// Metrics (all on one range image of beams x columns):
//   range_median_abs_m  median |rendered - real| range over rays where both return
//   chamfer_m           symmetric Chamfer distance: (mean NN distance rendered->real +
//                       mean NN distance real->rendered) / 2, metres, between the two range
//                       images turned back into points (range * the pixel's ray direction), so both
//                       clouds have the same angular sampling
//   drop_accuracy       fraction of all rays where rendered return / no-return equals the real one
//   intensity_rmse      RMSE of rendered intensity vs the real reflectance where both return
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "render/lidar/lidar_model.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/log/drive_log.h"

namespace streetsim {
class ThreadPool;
}

namespace streetsim::train {

struct LidarFrameMetrics {
  int frame = -1;                   // index into DriveLog::frames
  double range_median_abs_m = -1;   // -1: undefined (no ray where both return)
  double chamfer_m = -1;            // -1: a cloud is empty
  double drop_accuracy = -1;
  double intensity_rmse = -1;
  size_t rays = 0;                  // rays where both return (range and intensity metrics)
};

struct LidarEvalOptions {
  int columns = 2048;
  float return_alpha_threshold = 0.5f;
  // Chamfer queries per direction: at most this many points, taken at a fixed stride (every
  // point is in the search tree; only the queries are thinned), so results are deterministic.
  // 10,000: 3.551 m against 3.550 m with every point as a query on a KITTI frame (62k-Gaussian
  // scene), at an eighth of the cost (far queries make the kd-tree searches expensive).
  size_t chamfer_max_queries = 10000;
  // Rolling sweep: each column rendered from the ego pose at its own time, the log's ego
  // trajectory interpolated over the sweep. The sweep is centred on the scan's time stamp
  // (KITTI triggers its cameras, and stamps the synced scan, when the spinning LiDAR faces
  // forward, which is the middle column here). false: one static pose, the frame's.
  bool rolling_sweep = true;
};

struct LidarEvalResult {
  std::vector<LidarFrameMetrics> frames;
  LidarFrameMetrics mean;  // mean of each defined per-frame metric; rays summed
};

// Symmetric mean nearest-neighbour distance (metres) between two clouds; -1 when one is empty.
// Queries spread over `pool` when given (same result on any thread count).
double ChamferDistanceM(const std::vector<Eigen::Vector3f>& a, const std::vector<Eigen::Vector3f>& b,
                        size_t max_queries, ThreadPool* pool = nullptr);

// Compares a rendered range image (range 0 = no return) with the real one of the same model.
LidarFrameMetrics CompareRangeImages(const LidarModel& model, const std::vector<float>& rendered_range,
                                     const std::vector<float>& rendered_intensity,
                                     const std::vector<float>& real_range,
                                     const std::vector<float>& real_intensity, size_t chamfer_max_queries,
                                     ThreadPool* pool = nullptr);

// Renders and measures every listed frame that has a LiDAR observation (others are skipped).
// reflectance: per-Gaussian in [0, 1] or null (0.5 everywhere).
absl::StatusOr<LidarEvalResult> EvaluateLidar(const DriveLog& log, const std::vector<int>& frames,
                                              const GaussianStore& scene, const std::vector<float>* reflectance,
                                              const LidarEvalOptions& options = {});

// A dynamic (field) scene: the Gaussians to render at a time (dynamic_stage.h MakeStoreAtTime).
using StoreAtTime = std::function<absl::StatusOr<GaussianStore>(int64_t time_us)>;
// As above, with each frame's sweep rendered from store_at(frame time) (the camera metrics'
// time; one deformation for the whole ~100 ms sweep). An empty store_at renders `scene`.
// `reflectance` is per canonical Gaussian (the field moves Gaussians, it neither adds nor drops).
absl::StatusOr<LidarEvalResult> EvaluateLidar(const DriveLog& log, const std::vector<int>& frames,
                                              const GaussianStore& scene, const std::vector<float>* reflectance,
                                              const LidarEvalOptions& options, const StoreAtTime& store_at);

// The log's ego pose at time_us: translation interpolated linearly and rotation by slerp between
// the two frames around it, clamped to the first / last frame. The log must have frames.
Eigen::Isometry3d LogEgoPoseAt(const DriveLog& log, int64_t time_us);

// The per-Gaussian `reflectance` vertex property of a binary little-endian PLY, if it has one
// (nullopt otherwise). Errors for an unreadable file or a count other than expected_count.
absl::StatusOr<std::optional<std::vector<float>>> ReadPlyReflectance(const std::string& path,
                                                                     size_t expected_count);

}  // namespace streetsim::train
