#include "scene/log/scene_manifest.h"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim {
namespace {

nlohmann::json Matrix(const Eigen::Isometry3d& T) {
  nlohmann::json m = nlohmann::json::array();
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) m.push_back(T.matrix()(r, c));
  return m;
}

}  // namespace

std::string SceneManifestJson(const DriveLog& log, const std::string& name) {
  nlohmann::json j;
  j["name"] = name;
  if (!log.frames.empty()) {
    j["time_range_us"] = {log.frames.front().time_us, log.frames.back().time_us};
  }
  nlohmann::json cameras = nlohmann::json::array();
  for (const CameraSensor& cam : log.cameras) {
    const CameraIntrinsics& k = cam.intrinsics;
    cameras.push_back({{"sensor_id", cam.name}, {"width", k.width}, {"height", k.height},
                       {"fx", k.fx}, {"fy", k.fy}, {"cx", k.cx}, {"cy", k.cy},
                       {"T_ego_from_cam", Matrix(cam.T_ego_from_cam)}});
  }
  if (!cameras.empty()) j["cameras"] = cameras;
  nlohmann::json trajectory = nlohmann::json::array();
  int64_t last_us = 0;
  for (size_t i = 0; i < log.frames.size(); ++i) {
    const Frame& f = log.frames[i];
    // The server wants strictly increasing times; a log never repeats one, but stay safe.
    if (i > 0 && f.time_us <= last_us) continue;
    trajectory.push_back({{"time_us", f.time_us}, {"T_world_from_ego", Matrix(f.T_world_from_ego)}});
    last_us = f.time_us;
  }
  if (!trajectory.empty()) j["ego_trajectory"] = trajectory;
  nlohmann::json lidars = nlohmann::json::array();
  for (const LidarSensor& lidar : log.lidars) {
    lidars.push_back({{"sensor_id", lidar.name}, {"T_ego_from_lidar", Matrix(lidar.T_ego_from_lidar)}});
  }
  if (!lidars.empty()) j["lidars"] = lidars;
  return j.dump(1) + "\n";
}

absl::Status WriteSceneManifest(const DriveLog& log, const std::string& name, const std::string& path) {
  const std::string tmp = absl::StrCat(path, ".tmp", getpid());
  {
    std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
    f << SceneManifestJson(log, name);
    f.flush();
    if (!f.good()) {
      std::error_code ec;
      std::filesystem::remove(tmp, ec);
      return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
    }
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place"));
  }
  return absl::OkStatus();
}

}  // namespace streetsim
