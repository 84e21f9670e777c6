// The rolling sweep: a spinning LiDAR measures column c at time (c + 0.5) / columns of the sweep,
// so while the vehicle moves every column sees the scene from its own pose. The caller gives the
// sensor pose at the sweep's start and end; column c's pose interpolates them at
// s_c = (c + 0.5) / columns (slerp of the rotation, lerp of the translation), computed in double.
#pragma once

#include <vector>

#include <Eigen/Geometry>

#include "absl/status/status.h"

namespace streetsim {

struct LidarSweepPose {
  Eigen::Isometry3d T_world_from_lidar_start = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_world_from_lidar_end = Eigen::Isometry3d::Identity();

  static LidarSweepPose Static(const Eigen::Isometry3d& T_world_from_lidar) {
    return {T_world_from_lidar, T_world_from_lidar};
  }
  // Start and end equal exactly: one pose for every column (the renderer's static path).
  bool is_static() const { return T_world_from_lidar_start.matrix() == T_world_from_lidar_end.matrix(); }
};

// InvalidArgument unless both poses are finite rigid transforms.
absl::Status ValidateSweepPose(const LidarSweepPose& sweep);

// Column c's sensor pose (T_world_from_lidar), c in [0, columns).
Eigen::Isometry3d ColumnPose(const LidarSweepPose& sweep, int columns, int c);

// Every column's lidar_from_world: table[c * 12 + k], R row-major (k < 9) then t. A static sweep
// gives exactly T_world_from_lidar_start.inverse() in every entry.
void ColumnPoseTable(const LidarSweepPose& sweep, int columns, std::vector<double>* table);

}  // namespace streetsim
