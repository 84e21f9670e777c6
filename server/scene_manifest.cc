#include "server/scene_manifest.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim::server {
namespace {

using nlohmann::json;

absl::StatusOr<Eigen::Isometry3d> MatrixFromJson(const json& j, const std::string& what) {
  if (!j.is_array() || j.size() != 16) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": expected 16 numbers (row-major 4x4)"));
  }
  Eigen::Matrix4d m;
  for (int i = 0; i < 16; ++i) {
    if (!j[i].is_number()) return absl::InvalidArgumentError(absl::StrCat(what, ": not a number"));
    m(i / 4, i % 4) = j[i].get<double>();
    if (!std::isfinite(m(i / 4, i % 4))) {
      return absl::InvalidArgumentError(absl::StrCat(what, ": not finite"));
    }
  }
  const Eigen::Matrix3d R = m.topLeftCorner<3, 3>();
  if ((R * R.transpose() - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > 1e-4 ||
      R.determinant() < 0) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": rotation is not orthonormal"));
  }
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = m.topRightCorner<3, 1>();
  return T;
}

json MatrixToJson(const Eigen::Isometry3d& T) {
  json a = json::array();
  const Eigen::Matrix4d m = T.matrix();
  for (int i = 0; i < 16; ++i) a.push_back(m(i / 4, i % 4));
  return a;
}

}  // namespace

const RigCamera* SceneManifest::FindCamera(const std::string& id) const {
  for (const RigCamera& c : cameras) {
    if (c.sensor_id == id) return &c;
  }
  return nullptr;
}

std::optional<Eigen::Isometry3d> SceneManifest::EgoPoseAt(int64_t time_us) const {
  if (ego_trajectory.empty()) return std::nullopt;
  return InterpolateTrajectory(ego_trajectory, time_us);
}

Eigen::Isometry3d InterpolateTrajectory(const std::vector<TimedEgoPose>& poses, int64_t time_us) {
  if (time_us <= poses.front().time_us) return poses.front().T_world_from_ego;
  if (time_us >= poses.back().time_us) return poses.back().T_world_from_ego;
  auto it = std::upper_bound(poses.begin(), poses.end(), time_us,
                             [](int64_t t, const TimedEgoPose& p) { return t < p.time_us; });
  const TimedEgoPose& b = *it;
  const TimedEgoPose& a = *(it - 1);
  const double t = double(time_us - a.time_us) / double(b.time_us - a.time_us);
  return InterpolatePose(a.T_world_from_ego, b.T_world_from_ego, t);
}

std::vector<RigCamera> DefaultRig() {
  RigCamera cam;
  cam.sensor_id = "cam_front";
  cam.intrinsics = {1242, 375, 721.5, 721.5, 609.6, 172.9};
  Eigen::Matrix3d R;
  // Columns: the camera axes (x right, y down, z forward) in the FLU ego frame.
  R << 0, 0, 1,  //
      -1, 0, 0,  //
      0, -1, 0;
  cam.T_ego_from_cam.linear() = R;
  return {cam};
}

absl::StatusOr<SceneManifest> ParseSceneManifest(const std::string& json_text) {
  json j = json::parse(json_text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded() || !j.is_object()) {
    return absl::InvalidArgumentError("scene.json is not a JSON object");
  }
  SceneManifest m;
  try {
    if (j.contains("time_range_us")) {
      const json& r = j["time_range_us"];
      if (!r.is_array() || r.size() != 2 || !r[0].is_number_integer() || !r[1].is_number_integer()) {
        return absl::InvalidArgumentError("scene.json: time_range_us must be [start, end] integers");
      }
      m.has_time_range = true;
      m.start_us = r[0].get<int64_t>();
      m.end_us = r[1].get<int64_t>();
      if (m.end_us < m.start_us) return absl::InvalidArgumentError("scene.json: time range ends before it starts");
    }
    if (j.contains("cameras")) {
      for (const json& c : j["cameras"]) {
        RigCamera cam;
        cam.sensor_id = c.at("sensor_id").get<std::string>();
        if (cam.sensor_id.empty()) return absl::InvalidArgumentError("scene.json: empty sensor_id");
        if (m.FindCamera(cam.sensor_id)) {
          return absl::InvalidArgumentError(absl::StrCat("scene.json: duplicate camera ", cam.sensor_id));
        }
        v1::PinholeIntrinsics k;
        k.set_width(c.at("width").get<int>());
        k.set_height(c.at("height").get<int>());
        k.set_fx(c.at("fx").get<double>());
        k.set_fy(c.at("fy").get<double>());
        k.set_cx(c.at("cx").get<double>());
        k.set_cy(c.at("cy").get<double>());
        absl::StatusOr<Intrinsics> intr = IntrinsicsFromProto(k, "scene.json camera " + cam.sensor_id);
        if (!intr.ok()) return intr.status();
        cam.intrinsics = *intr;
        if (c.contains("T_ego_from_cam")) {
          absl::StatusOr<Eigen::Isometry3d> T = MatrixFromJson(c["T_ego_from_cam"], "T_ego_from_cam");
          if (!T.ok()) return T.status();
          cam.T_ego_from_cam = *T;
        } else {
          cam.T_ego_from_cam = DefaultRig()[0].T_ego_from_cam;
        }
        m.cameras.push_back(cam);
      }
    }
    if (j.contains("ego_trajectory")) {
      for (const json& p : j["ego_trajectory"]) {
        TimedEgoPose tp;
        tp.time_us = p.at("time_us").get<int64_t>();
        absl::StatusOr<Eigen::Isometry3d> T = MatrixFromJson(p.at("T_world_from_ego"), "T_world_from_ego");
        if (!T.ok()) return T.status();
        tp.T_world_from_ego = *T;
        if (!m.ego_trajectory.empty() && tp.time_us <= m.ego_trajectory.back().time_us) {
          return absl::InvalidArgumentError("scene.json: ego_trajectory times must increase");
        }
        m.ego_trajectory.push_back(tp);
      }
    }
    if (j.contains("lidars")) {
      for (const json& l : j["lidars"]) {
        RigLidar lidar;
        lidar.sensor_id = l.at("sensor_id").get<std::string>();
        if (lidar.sensor_id.empty()) return absl::InvalidArgumentError("scene.json: empty lidar sensor_id");
        if (l.contains("T_ego_from_lidar")) {
          absl::StatusOr<Eigen::Isometry3d> T = MatrixFromJson(l["T_ego_from_lidar"], "T_ego_from_lidar");
          if (!T.ok()) return T.status();
          lidar.T_ego_from_lidar = *T;
        }
        if (l.contains("sweep_duration_us")) {
          lidar.sweep_duration_us = l["sweep_duration_us"].get<int64_t>();
          if (lidar.sweep_duration_us < 0 || lidar.sweep_duration_us > 10'000'000) {
            return absl::InvalidArgumentError("scene.json: lidar sweep_duration_us must be in [0, 10 s]");
          }
        }
        m.lidars.push_back(lidar);
      }
    }
  } catch (const json::exception& e) {
    return absl::InvalidArgumentError(absl::StrCat("scene.json: ", e.what()));
  }
  if (m.cameras.empty()) m.cameras = DefaultRig();
  if (!m.has_time_range && !m.ego_trajectory.empty()) {
    m.has_time_range = true;
    m.start_us = m.ego_trajectory.front().time_us;
    m.end_us = m.ego_trajectory.back().time_us;
  }
  return m;
}

absl::StatusOr<SceneManifest> ReadSceneManifest(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat(path, ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  absl::StatusOr<SceneManifest> m = ParseSceneManifest(ss.str());
  if (!m.ok()) return absl::InvalidArgumentError(absl::StrCat(path, ": ", m.status().message()));
  return m;
}

std::string SceneManifestToJson(const SceneManifest& m) {
  json j = json::object();
  if (m.has_time_range) j["time_range_us"] = {m.start_us, m.end_us};
  json cams = json::array();
  for (const RigCamera& c : m.cameras) {
    cams.push_back({{"sensor_id", c.sensor_id}, {"width", c.intrinsics.width},
                    {"height", c.intrinsics.height}, {"fx", c.intrinsics.fx},
                    {"fy", c.intrinsics.fy}, {"cx", c.intrinsics.cx}, {"cy", c.intrinsics.cy},
                    {"T_ego_from_cam", MatrixToJson(c.T_ego_from_cam)}});
  }
  j["cameras"] = cams;
  json traj = json::array();
  for (const TimedEgoPose& p : m.ego_trajectory) {
    traj.push_back({{"time_us", p.time_us}, {"T_world_from_ego", MatrixToJson(p.T_world_from_ego)}});
  }
  if (!traj.empty()) j["ego_trajectory"] = traj;
  json lidars = json::array();
  for (const RigLidar& l : m.lidars) {
    lidars.push_back({{"sensor_id", l.sensor_id}, {"T_ego_from_lidar", MatrixToJson(l.T_ego_from_lidar)},
                      {"sweep_duration_us", l.sweep_duration_us}});
  }
  if (!lidars.empty()) j["lidars"] = lidars;
  return j.dump(1);
}

}  // namespace streetsim::server
