// Structure from the log's own poses, for camera-only logs that bring no sparse points (a KITTI
// odometry sequence): ORB features matched between nearby images (one camera at frame gaps 1 and
// 2, and the rig's cameras at the same frame), each match triangulated with the known poses and
// kept only where it is in front of both views, reprojects within a pixel or two in both and its
// rays meet at a useful angle. Known poses make this a filter, not a reconstruction: nothing here
// estimates a pose, so a log's pose errors show as fewer points, never as a warped scene.
//
// Random points in the frusta (the fallback before this) leave the static model at 12-13 dB
// held-out on the odometry excerpt; docs/training.md "Initial scene" has the comparison.
#pragma once

#include <cstddef>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct TriangulationOptions {
  FrameRange frames;
  int features_per_image = 4000;
  std::vector<int> frame_gaps = {1, 2};  // one camera's image against its own this many frames on
  double ratio_test = 0.8;               // Lowe's: best match's distance below this x the second's
  double max_reprojection_px = 2.0;      // in both images (full-resolution pixels)
  double min_angle_deg = 1.0;            // between the two rays at the point
  double min_depth_m = 1.0, max_depth_m = 100.0;
  double voxel_m = 0.15;                 // points in one voxel merge (mean position and colour)
};

struct TriangulatedPoints {
  std::vector<Eigen::Vector3f> points;
  std::vector<Eigen::Vector3f> rgb;  // [0,1], the mean of the pixels it was matched at
  int image_pairs = 0;
  size_t matches = 0;       // after the ratio test
  size_t triangulated = 0;  // that passed every check (before the voxel merge)
};

// InvalidArgument when no frame is selected; a missing or unreadable image is the loader's error.
absl::StatusOr<TriangulatedPoints> TriangulateWithKnownPoses(const DriveLog& log, const TriangulationOptions& options);

// The midpoint of two rays' closest approach; false when they are (nearly) parallel.
bool TriangulateMidpoint(const Eigen::Vector3d& origin_a, const Eigen::Vector3d& dir_a, const Eigen::Vector3d& origin_b,
                         const Eigen::Vector3d& dir_b, Eigen::Vector3d* point);

}  // namespace streetsim
