// LiDAR beside the cameras (docs/server.md "LiDAR"): validation of a v1::LidarRequest against a
// scene's rig, the sweep's poses, and the wire form of a rendered sweep. Rendering itself is
// RenderCore's (render/lidar's public API only).
#pragma once

#include <cstdint>
#include <string>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "render/lidar/lidar_sweep.h"
#include "server/scene_manifest.h"
#include "streetsim/v1/common.pb.h"

namespace streetsim::server {

struct LidarJob {
  std::string sensor_id;
  LidarModel model;                 // KITTI HDL-64E table, the request's columns and ranges
  LidarSweepPose sweep;             // sensor poses at the sweep's start and end
  LidarRenderOptions options;       // reflectance is filled in by the renderer's caller
  v1::LidarPointFrame points_frame = v1::LIDAR_POINT_FRAME_SENSOR;
};

// INVALID_ARGUMENT for columns outside 1..65536 (0 = 2048), non-finite or negative ranges,
// min >= max, a threshold outside (0, 1], an unknown points frame or a bad mounting pose. The
// sensor is the scene's first LiDAR (its mounting and sweep duration), else one at the ego origin.
absl::StatusOr<LidarJob> ResolveLidar(const v1::LidarRequest& request, const SceneManifest& manifest);

// Places the sweep: start at T_world_from_ego_start * mounting, end likewise (equal poses: a
// static sweep); points time from time_us.
void PlaceLidar(const Eigen::Isometry3d& T_world_from_ego_start, const Eigen::Isometry3d& T_world_from_ego_end,
                int64_t time_us, LidarJob* job);
// The sweep is given directly as the LiDAR's own (static) pose.
void PlaceLidarAt(const Eigen::Isometry3d& T_world_from_lidar, int64_t time_us, LidarJob* job);

// The wire result (little-endian float32 arrays; this server only runs on little-endian hosts).
void LidarResultToProto(const LidarJob& job, const LidarRenderOutput& out, v1::LidarResult* result);

}  // namespace streetsim::server
