// scene.json: what a scene directory says about the log it was built from, so that the server
// (server/scene_manifest.h parses it) serves the log's time range, camera rig and ego trajectory.
//
//   {"name": .., "time_range_us": [START, END],
//    "cameras": [{"sensor_id", "width", "height", "fx", "fy", "cx", "cy",
//                 "T_ego_from_cam": [16 numbers, row-major]}],
//    "ego_trajectory": [{"time_us", "T_world_from_ego": [16 numbers, row-major]}],
//    "lidars": [{"sensor_id", "T_ego_from_lidar": [16 numbers, row-major]}]}
#pragma once

#include <string>

#include "absl/status/status.h"
#include "scene/log/drive_log.h"

namespace streetsim {

// The manifest of a log. Only pinhole cameras are listed (the renderer is pinhole-only; distorted
// COLMAP cameras are listed with the pinhole the images are undistorted onto: the same K).
std::string SceneManifestJson(const DriveLog& log, const std::string& name);

// Writes it atomically (temporary file + rename).
absl::Status WriteSceneManifest(const DriveLog& log, const std::string& name, const std::string& path);

}  // namespace streetsim
