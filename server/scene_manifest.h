// A server scene's description: scene.json next to scene.ply, or the defaults of a bare .ply.
//
// scene.json (every key optional):
//   {"name": "kitti_0001",
//    "time_range_us": [START, END],
//    "cameras": [{"sensor_id": "cam_front", "width": 1242, "height": 375, "fx": .., "fy": ..,
//                 "cx": .., "cy": .., "T_ego_from_cam": [16 numbers, row-major 4x4]}],
//    "ego_trajectory": [{"time_us": T, "T_world_from_ego": [16 numbers, row-major]}],
//    "lidars": [{"sensor_id": "velodyne_points", "T_ego_from_lidar": [16 numbers, row-major],
//                "sweep_duration_us": 100000}]}
// LiDAR frame: x forward, y left, z up. Without lidars a LiDAR request gets one at the ego origin.
// Frames: ego FLU (x forward, y left, z up), camera OpenCV (x right, y down, z forward).
// Without cameras the default rig is one KITTI-like camera (see DefaultRig).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "server/proto_convert.h"

namespace streetsim::server {

struct RigCamera {
  std::string sensor_id;
  Intrinsics intrinsics;
  Eigen::Isometry3d T_ego_from_cam = Eigen::Isometry3d::Identity();
};

struct RigLidar {
  std::string sensor_id = "lidar";
  Eigen::Isometry3d T_ego_from_lidar = Eigen::Isometry3d::Identity();
  int64_t sweep_duration_us = 100'000;
};

struct TimedEgoPose {
  int64_t time_us = 0;
  Eigen::Isometry3d T_world_from_ego = Eigen::Isometry3d::Identity();
};

struct SceneManifest {
  bool has_time_range = false;
  int64_t start_us = 0;
  int64_t end_us = 0;
  std::vector<RigCamera> cameras;
  std::vector<TimedEgoPose> ego_trajectory;  // sorted by time
  std::vector<RigLidar> lidars;              // empty: none declared (LiDAR requests use RigLidar{})
  // The learned sky colour of a trained scene (train_meta.json beside scene.ply, set by the
  // registry, not part of scene.json): camera renders use it unless the request sets a background.
  std::optional<Eigen::Vector3f> background;

  const RigCamera* FindCamera(const std::string& id) const;
  // The log's ego pose at time_us (interpolated, clamped to the ends); nullopt without one.
  std::optional<Eigen::Isometry3d> EgoPoseAt(int64_t time_us) const;
};

// One camera "cam_front": 1242x375, fx = fy = 721.5, cx = 609.6, cy = 172.9 at the ego origin
// looking along ego +x (ego FLU -> OpenCV camera).
std::vector<RigCamera> DefaultRig();

absl::StatusOr<SceneManifest> ParseSceneManifest(const std::string& json_text);
absl::StatusOr<SceneManifest> ReadSceneManifest(const std::string& path);
std::string SceneManifestToJson(const SceneManifest& manifest);

// Interpolates an ego trajectory at time_us (clamped). `poses` sorted by time, non-empty.
Eigen::Isometry3d InterpolateTrajectory(const std::vector<TimedEgoPose>& poses, int64_t time_us);

}  // namespace streetsim::server
