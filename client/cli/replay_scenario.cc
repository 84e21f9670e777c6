#include "client/cli/replay_scenario.h"

#include <cmath>
#include <limits>
#include <type_traits>

#include "absl/strings/str_cat.h"
#include "client/cpp/streetsim_client.h"
#include "scene/common/checked_file.h"

namespace streetsim {
namespace {

using json = nlohmann::json;

constexpr std::uintmax_t kMaxScenarioBytes = 16 << 20;  // a scenario of 100 000 posed steps fits
constexpr int kMaxSteps = 100000;

template <typename T>
const char* TypeName() {
  if constexpr (std::is_same_v<T, bool>) return "true or false";
  if constexpr (std::is_same_v<T, std::string>) return "a string";
  if constexpr (std::is_integral_v<T> && std::is_unsigned_v<T>) return "a non-negative integer";
  if constexpr (std::is_integral_v<T>) return "an integer";
  if constexpr (std::is_floating_point_v<T>) return "a number";
  return "a list of strings";
}

// j[key] into *out when present (else *out keeps its default); InvalidArgument naming
// `where` + key when the value has another type or does not fit T.
template <typename T>
absl::Status Read(const json& j, const std::string& where, const char* key, T* out) {
  if (!j.contains(key)) return absl::OkStatus();
  const json& v = j[key];
  bool ok = false;
  if constexpr (std::is_same_v<T, bool>) {
    ok = v.is_boolean();
  } else if constexpr (std::is_same_v<T, std::string>) {
    ok = v.is_string();
  } else if constexpr (std::is_integral_v<T> && std::is_unsigned_v<T>) {
    ok = v.is_number_unsigned();
  } else if constexpr (std::is_integral_v<T>) {
    ok = (v.is_number_unsigned() && v.get<uint64_t>() <= static_cast<uint64_t>(std::numeric_limits<T>::max())) ||
         (v.is_number_integer() && !v.is_number_unsigned() && v.get<int64_t>() >= std::numeric_limits<T>::min() &&
          v.get<int64_t>() <= std::numeric_limits<T>::max());
  } else if constexpr (std::is_floating_point_v<T>) {
    ok = v.is_number() && std::isfinite(v.get<double>());
  } else {
    ok = v.is_array();
    for (const json& e : v) ok = ok && e.is_string();
  }
  if (!ok) return absl::InvalidArgumentError(absl::StrCat(where, "\"", key, "\" must be ", TypeName<T>()));
  *out = v.get<T>();
  return absl::OkStatus();
}

absl::StatusOr<Eigen::Isometry3d> MatrixFromJson(const json& j) {
  if (!j.is_array() || j.size() != 16) return absl::InvalidArgumentError("a pose is 16 numbers (row-major 4x4)");
  Eigen::Matrix4d m;
  for (int i = 0; i < 16; ++i) {
    if (!j[i].is_number() || !std::isfinite(j[i].get<double>())) {
      return absl::InvalidArgumentError("a pose is 16 finite numbers");
    }
    m(i / 4, i % 4) = j[i].get<double>();
  }
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = m.topLeftCorner<3, 3>();
  T.translation() = m.topRightCorner<3, 1>();
  return T;
}

// The log's ego trajectory at each step, offset in the ego frame (FLU).
absl::StatusOr<std::vector<Eigen::Isometry3d>> LogEgoPoses(const json& ego, const v1::Scene& scene, int num_steps,
                                                           int64_t t0, int64_t dt) {
  if (scene.ego_trajectory_size() == 0) {
    return absl::InvalidArgumentError("ego mode \"log\" needs a scene with an ego trajectory");
  }
  double lat = 0, lon = 0;
  if (absl::Status s = Read(ego, "ego.", "lateral_offset_m", &lat); !s.ok()) return s;
  if (absl::Status s = Read(ego, "ego.", "longitudinal_offset_m", &lon); !s.ok()) return s;
  const auto& traj = scene.ego_trajectory();
  std::vector<Eigen::Isometry3d> poses;
  for (int k = 0; k < num_steps; ++k) {
    const int64_t t = t0 + k * dt;
    int i = 0;
    while (i + 1 < traj.size() && traj[i + 1].time_us() <= t) ++i;
    Eigen::Isometry3d T = client::FromPose(traj[i].t_world_from_ego());
    if (i + 1 < traj.size() && t > traj[i].time_us()) {
      const double a = double(t - traj[i].time_us()) / double(traj[i + 1].time_us() - traj[i].time_us());
      const Eigen::Isometry3d B = client::FromPose(traj[i + 1].t_world_from_ego());
      T.translation() = (1 - a) * T.translation() + a * B.translation();
      T.linear() = Eigen::Quaterniond(T.rotation()).slerp(a, Eigen::Quaterniond(B.rotation())).toRotationMatrix();
    }
    T.translation() += T.linear() * Eigen::Vector3d(lon, lat, 0);
    poses.push_back(T);
  }
  return poses;
}

}  // namespace

absl::StatusOr<ReplayScenario> ReadReplayScenario(const std::string& path) {
  absl::StatusOr<std::string> text = checked_file::ReadBounded(path, kMaxScenarioBytes);
  if (absl::IsOutOfRange(text.status())) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": larger than 16 MiB, not a scenario"));
  }
  if (!text.ok()) return absl::InvalidArgumentError(absl::StrCat(path, ": cannot open"));
  const json sc = json::parse(*text, nullptr, /*allow_exceptions=*/false);
  if (sc.is_discarded() || !sc.is_object()) return absl::InvalidArgumentError("scenario is not a JSON object");
  ReplayScenario r;
  std::string server;
  absl::Status s = Read(sc, "", "server", &server);
  if (s.ok() && sc.contains("server")) r.server = server;
  if (s.ok()) s = Read(sc, "", "scene", &r.scene);
  if (s.ok()) s = Read(sc, "", "num_steps", &r.num_steps);
  if (s.ok()) s = Read(sc, "", "step_dt_us", &r.step_dt_us);
  if (s.ok()) s = Read(sc, "", "start_time_us", &r.start_time_us);
  if (s.ok()) s = Read(sc, "", "seed", &r.seed);
  if (s.ok()) s = Read(sc, "", "jpeg", &r.jpeg);
  if (s.ok()) s = Read(sc, "", "depth", &r.depth);
  if (s.ok()) s = Read(sc, "", "sensors", &r.sensors);
  if (s.ok()) s = Read(sc, "", "width", &r.width);
  if (s.ok()) s = Read(sc, "", "height", &r.height);
  double fps = 0;
  if (s.ok()) s = Read(sc, "", "video_fps", &fps);
  if (!s.ok()) return absl::InvalidArgumentError(absl::StrCat("scenario: ", s.message()));
  if (r.scene.empty() || r.num_steps <= 0 || r.num_steps > kMaxSteps) {
    return absl::InvalidArgumentError("scenario needs \"scene\" and \"num_steps\" in 1..100000");
  }
  if (r.step_dt_us <= 0 || r.step_dt_us > int64_t{3600} * 1000000) {
    return absl::InvalidArgumentError("scenario: \"step_dt_us\" must be in 1..3600000000 (one hour)");
  }
  if (r.start_time_us < 0) return absl::InvalidArgumentError("scenario: \"start_time_us\" must be >= 0");
  if (r.width < 0 || r.height < 0) return absl::InvalidArgumentError("scenario: \"width\" / \"height\" must be >= 0");
  if (sc.contains("video_fps")) {
    if (!(fps > 0 && fps <= 1000)) return absl::InvalidArgumentError("scenario: \"video_fps\" must be in (0, 1000]");
    r.video_fps = fps;
  }
  r.ego = sc.value("ego", json{{"mode", "log"}});
  if (!r.ego.is_object()) return absl::InvalidArgumentError("scenario: \"ego\" must be an object");
  if (sc.contains("actors")) r.actors = sc["actors"];
  return r;
}

absl::StatusOr<std::vector<Eigen::Isometry3d>> ScenarioEgoPoses(const ReplayScenario& sc, const v1::Scene& scene,
                                                                int64_t t0) {
  std::string mode = "log";
  if (absl::Status s = Read(sc.ego, "ego.", "mode", &mode); !s.ok()) return s;
  const int64_t dt = sc.step_dt_us;
  if (mode == "log") return LogEgoPoses(sc.ego, scene, sc.num_steps, t0, dt);
  std::vector<Eigen::Isometry3d> poses;
  if (mode == "poses") {
    const json list = sc.ego.value("poses", json::array());
    if (!list.is_array()) return absl::InvalidArgumentError("ego.poses must be a list of poses");
    for (const json& p : list) {
      absl::StatusOr<Eigen::Isometry3d> T = MatrixFromJson(p);
      if (!T.ok()) return absl::InvalidArgumentError(absl::StrCat("ego.poses: ", T.status().message()));
      poses.push_back(*T);
    }
    if (static_cast<int>(poses.size()) < sc.num_steps) {
      return absl::InvalidArgumentError("ego.poses has fewer poses than num_steps");
    }
    return poses;
  }
  if (mode == "straight") {
    absl::StatusOr<Eigen::Isometry3d> start = MatrixFromJson(sc.ego.value("start", json::array()));
    if (!start.ok()) return absl::InvalidArgumentError(absl::StrCat("ego.start: ", start.status().message()));
    double v = 5.0;
    if (absl::Status s = Read(sc.ego, "ego.", "speed_mps", &v); !s.ok()) return s;
    for (int k = 0; k < sc.num_steps; ++k) {
      Eigen::Isometry3d T = *start;
      T.translation() += start->linear() * Eigen::Vector3d(v * k * dt * 1e-6, 0, 0);
      poses.push_back(T);
    }
    return poses;
  }
  return absl::InvalidArgumentError("ego.mode must be log, poses or straight");
}

absl::StatusOr<std::vector<ScenarioEdit>> ScenarioActorEdits(const json& list, const v1::Scene& scene,
                                                            const std::vector<Eigen::Isometry3d>& ego, int64_t t0,
                                                            int64_t dt) {
  std::vector<ScenarioEdit> out;
  if (!list.is_array()) return absl::InvalidArgumentError("\"actors\" is a list of edits");
  for (size_t i = 0; i < list.size(); ++i) {
    const json& j = list[i];
    const std::string where = absl::StrCat("actors[", i, "]");
    int actor_id = -1;
    if (!j.is_object() || !j.contains("actor_id") || !Read(j, where + ".", "actor_id", &actor_id).ok()) {
      return absl::InvalidArgumentError(absl::StrCat(where, " needs \"actor_id\""));
    }
    ScenarioEdit e;
    std::string kind;
    if (absl::Status s = Read(j, where + ".", "from_step", &e.from_step); !s.ok()) return s;
    if (absl::Status s = Read(j, where + ".", "edit", &kind); !s.ok()) return s;
    e.edit.set_kind(kind == "remove"   ? v1::ACTOR_EDIT_REMOVE
                    : kind == "move"   ? v1::ACTOR_EDIT_MOVE
                    : kind == "insert" ? v1::ACTOR_EDIT_INSERT
                                       : v1::ACTOR_EDIT_KIND_UNSPECIFIED);
    if (e.edit.kind() == v1::ACTOR_EDIT_KIND_UNSPECIFIED) {
      return absl::InvalidArgumentError(absl::StrCat(where, ".edit must be remove, move or insert"));
    }
    e.edit.set_actor_id(actor_id);
    const v1::Actor* actor = nullptr;
    for (const v1::Actor& a : scene.actors()) {
      if (a.actor_id() == e.edit.actor_id()) actor = &a;
    }
    if (actor == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": the scene has no actor ", e.edit.actor_id(),
                                                     " (streetsim scenes --info ", scene.name(), ")"));
    }
    const json path = j.value("path", json::array());
    if (!path.is_array()) return absl::InvalidArgumentError(absl::StrCat(where, ".path must be a list of poses"));
    const std::string pose_help = absl::StrCat(
        where, ".path: a pose is {\"step\": K in the replay, \"ego_xyz_m\": [x, y(, z)], \"yaw_deg\": Y} or "
               "{\"time_us\", \"T_world_from_actor\"}");
    for (const json& p : path) {
      if (!p.is_object()) return absl::InvalidArgumentError(pose_help);
      v1::ActorPose* pose = e.edit.add_trajectory();
      if (p.contains("T_world_from_actor")) {
        absl::StatusOr<Eigen::Isometry3d> T = MatrixFromJson(p["T_world_from_actor"]);
        if (!T.ok()) return absl::InvalidArgumentError(absl::StrCat(where, ".path: ", T.status().message()));
        int64_t time_us = 0;
        if (absl::Status s = Read(p, where + ".path.", "time_us", &time_us); !s.ok()) return s;
        pose->set_time_us(time_us);
        *pose->mutable_t_world_from_actor() = client::ToPose(*T);
        continue;
      }
      int step = -1;
      double yaw_deg = 0;
      const json xyz = p.value("ego_xyz_m", json::array());
      if (!Read(p, "", "step", &step).ok() || !Read(p, "", "yaw_deg", &yaw_deg).ok() || step < 0 ||
          step >= static_cast<int>(ego.size()) || !xyz.is_array() || xyz.size() < 2 || !xyz[0].is_number() ||
          !xyz[1].is_number()) {
        return absl::InvalidArgumentError(pose_help);
      }
      double z = 0;
      if (xyz.size() > 2 && xyz[2].is_number()) {
        z = xyz[2].get<double>();
      } else if (actor->trajectory_size() > 0) {
        // The log's height of the actor above the ego at its first scan.
        const Eigen::Isometry3d first = client::FromPose(actor->trajectory(0).t_world_from_actor());
        z = (ego.front().inverse() * first).translation().z();
      }
      Eigen::Isometry3d local = Eigen::Isometry3d::Identity();
      local.translation() = Eigen::Vector3d(xyz[0].get<double>(), xyz[1].get<double>(), z);
      local.linear() = Eigen::AngleAxisd(yaw_deg * M_PI / 180, Eigen::Vector3d::UnitZ()).toRotationMatrix();
      pose->set_time_us(t0 + step * dt);
      *pose->mutable_t_world_from_actor() = client::ToPose(ego[step] * local);
    }
    out.push_back(std::move(e));
  }
  return out;
}

}  // namespace streetsim
