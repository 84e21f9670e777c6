// Pinhole camera in the OpenCV convention (x right, y down, z forward), undistorted.
#pragma once

#include <Eigen/Geometry>

#include "absl/status/status.h"

namespace streetsim {

inline constexpr int kMaxImageSide = 4096;

struct PinholeCamera {
  int width = 0;
  int height = 0;
  // Pixels, OpenCV convention: the centre of pixel (u, v) is the image point (u, v), so a centred
  // principal point is ((width - 1) / 2, (height - 1) / 2). Pixel (u, v) samples exactly there.
  double fx = 0, fy = 0, cx = 0, cy = 0;
  Eigen::Isometry3d T_world_from_cam = Eigen::Isometry3d::Identity();

  // Size within 1..kMaxImageSide, positive finite focal lengths, finite principal point, a finite
  // rigid pose (rotation orthonormal to 1e-6).
  absl::Status Validate() const;
};

}  // namespace streetsim
