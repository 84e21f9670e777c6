// LiDAR odometry: scan-to-scan point-to-plane ICP with a constant-velocity initial guess.
//
// Each scan is range-filtered (the ego car's own roof returns and far, sparse returns are
// dropped), voxel-downsampled, and registered onto the previous scan's planar points (normals from
// PCA of the k nearest neighbours, points on edges and clutter rejected). Gauss-Newton on
// the point-to-plane residual with Huber weights and a shrinking correspondence radius.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"
#include "scene/log/kdtree.h"

namespace streetsim {

struct LidarOdometryOptions {
  double min_range_m = 3.0;    // KITTI: the car's roof and the sensor mount lie inside 3 m
  double max_range_m = 40.0;   // beyond ~40 m HDL-64 returns are sparse and noisy planes
  double source_voxel_m = 0.5;
  double target_voxel_m = 0.25;
  int normal_neighbours = 10;
  double max_planarity = 0.08;  // smallest / sum of eigenvalues above this: not a plane
  int max_iterations = 30;
  double initial_correspondence_m = 1.5;
  double final_correspondence_m = 0.4;
  double huber_m = 0.1;
  int first_frame = 0;  // frame range [first_frame, last_frame) of the log; -1: to the end
  int last_frame = -1;
};

// A registration target: planar points with unit normals and their k-d tree.
struct PlaneCloud {
  std::vector<Eigen::Vector3f> points;
  std::vector<Eigen::Vector3f> normals;
  KdTree3 tree;
  PlaneCloud() = default;
  PlaneCloud(const PlaneCloud&) = delete;  // the tree points into `points`
  PlaneCloud& operator=(const PlaneCloud&) = delete;
};

// Range-filters `scan` (sensor frame) to [min_range_m, max_range_m].
std::vector<Eigen::Vector3f> RangeFilter(const std::vector<Eigen::Vector3f>& scan, double min_range_m,
                                         double max_range_m);
// Downsampled planar points with normals (built in place: the tree refers to cloud->points).
void BuildPlaneCloud(const std::vector<Eigen::Vector3f>& points, const LidarOdometryOptions& options,
                     PlaneCloud* cloud);

struct IcpResult {
  Eigen::Isometry3d T_target_from_source = Eigen::Isometry3d::Identity();
  int iterations = 0;
  int inliers = 0;
  double rmse_m = 0;  // point-to-plane, inliers at the final radius
  bool converged = false;
};
IcpResult PointToPlaneIcp(const PlaneCloud& target, const std::vector<Eigen::Vector3f>& source,
                          const Eigen::Isometry3d& initial, const LidarOdometryOptions& options);

struct LidarOdometryResult {
  std::vector<int> frames;                          // log frame indices covered
  std::vector<Eigen::Isometry3d> T_world_from_ego;  // world = ego at the first covered frame
  std::vector<IcpResult> icp;                       // per frame (frame 0: identity)
  double ms_per_scan = 0;                           // load + filter + normals + ICP
  std::vector<std::string> problems;
};

// Odometry over the log's first LiDAR; frame poses in the log are ignored.
absl::StatusOr<LidarOdometryResult> RunLidarOdometry(const DriveLog& log,
                                                     const LidarOdometryOptions& options = {});

// Estimate vs reference over the same frames, both re-anchored at their first pose.
struct TrajectoryComparison {
  double reference_distance_m = 0;
  double final_translation_error_m = 0;
  double max_translation_error_m = 0;
  double final_rotation_error_deg = 0;
  // final_translation_error_m per 100 m of reference distance (percent); from a short log this is
  // an extrapolation (stated by the caller).
  double drift_percent = 0;
  double mean_relative_translation_error_m = 0;  // per frame step
  double mean_relative_rotation_error_deg = 0;
};
TrajectoryComparison CompareTrajectories(const std::vector<Eigen::Isometry3d>& estimate,
                                         const std::vector<Eigen::Isometry3d>& reference);

}  // namespace streetsim
