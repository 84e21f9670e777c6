// A server scene's description: scene.json next to scene.ply, or the defaults of a bare .ply.
//
// scene.json (every key optional):
//   {"name": "kitti_0001",
//    "time_range_us": [START, END],
//    "cameras": [{"sensor_id": "cam_front", "width": 1242, "height": 375, "fx": .., "fy": ..,
//                 "cx": .., "cy": .., "T_ego_from_cam": [16 numbers, row-major 4x4]}],
//    "ego_trajectory": [{"time_us": T, "T_world_from_ego": [16 numbers, row-major]}]}
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
