#include "scene/actors/actor_set.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "scene/actors/rigid_gaussians.h"
#include "scene/common/checked_file.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim::actors {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// Far above any log's actor count or any actor's Gaussians: a damaged file cannot ask for more.
constexpr size_t kMaxActors = 10000;
constexpr size_t kMaxPoses = 1000000;

json PoseJson(const TimedPose& p) {
  const Eigen::Vector3d t = p.T_world_from_actor.translation();
  const Eigen::Quaterniond q(p.T_world_from_actor.rotation());
  return json{{"time_us", p.time_us}, {"t", {t.x(), t.y(), t.z()}}, {"q", {q.w(), q.x(), q.y(), q.z()}}};
}

absl::StatusOr<TimedPose> PoseFromJson(const json& j) {
  TimedPose p;
  if (!j.is_object() || !j.contains("time_us") || !j["time_us"].is_number_integer() || !j.contains("t") ||
      !j["t"].is_array() || j["t"].size() != 3 || !j.contains("q") || !j["q"].is_array() || j["q"].size() != 4) {
    return absl::DataLossError("a pose needs time_us, t[3] and q[4]");
  }
  p.time_us = j["time_us"].get<int64_t>();
  double t[3], q[4];
  for (int a = 0; a < 3; ++a) {
    if (!j["t"][a].is_number()) return absl::DataLossError("a pose's t is not numbers");
    t[a] = j["t"][a].get<double>();
  }
  for (int a = 0; a < 4; ++a) {
    if (!j["q"][a].is_number()) return absl::DataLossError("a pose's q is not numbers");
    q[a] = j["q"][a].get<double>();
  }
  const double norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!std::isfinite(t[0] + t[1] + t[2]) || !std::isfinite(norm) || std::abs(norm - 1) > 1e-6) {
    return absl::DataLossError("a pose is not finite or its quaternion is not unit");
  }
  p.T_world_from_actor = Eigen::Isometry3d::Identity();
  p.T_world_from_actor.linear() = Eigen::Quaterniond(q[0], q[1], q[2], q[3]).normalized().toRotationMatrix();
  p.T_world_from_actor.translation() = Eigen::Vector3d(t[0], t[1], t[2]);
  return p;
}

absl::StatusOr<std::vector<uint32_t>> RowsFromJson(const json& j, size_t bound) {
  if (!j.is_array() || j.size() > bound) return absl::DataLossError("rows are not an array of scene rows");
  std::vector<uint32_t> rows;
  rows.reserve(j.size());
  for (const json& r : j) {
    if (!r.is_number_unsigned() || r.get<uint64_t>() >= bound) return absl::DataLossError("a row is not in the scene");
    rows.push_back(r.get<uint32_t>());
  }
  return rows;
}

absl::StatusOr<Actor> ActorFromJson(const json& j, size_t scene_gaussians) {
  Actor a;
  if (!j.is_object() || !j.contains("id") || !j["id"].is_number_integer() || !j.contains("trajectory") ||
      !j["trajectory"].is_array() || !j.contains("half_extent_m") || !j["half_extent_m"].is_array() ||
      j["half_extent_m"].size() != 3 || !j.contains("body_rows") || !j.contains("ghost_rows")) {
    return absl::DataLossError("an actor needs id, trajectory, half_extent_m[3], body_rows and ghost_rows");
  }
  a.id = j["id"].get<int>();
  a.track_id = j.value("track", 0);
  a.reference_time_us = j.value("reference_time_us", int64_t{0});
  if (j["trajectory"].empty() || j["trajectory"].size() > kMaxPoses) {
    return absl::DataLossError(absl::StrCat("actor ", a.id, ": its trajectory is empty or absurdly long"));
  }
  for (const json& p : j["trajectory"]) {
    absl::StatusOr<TimedPose> pose = PoseFromJson(p);
    if (!pose.ok()) return absl::DataLossError(absl::StrCat("actor ", a.id, ": ", pose.status().message()));
    if (!a.trajectory.empty() && pose->time_us <= a.trajectory.back().time_us) {
      return absl::DataLossError(absl::StrCat("actor ", a.id, ": trajectory times do not increase"));
    }
    a.trajectory.push_back(*pose);
  }
  for (int k = 0; k < 3; ++k) {
    if (!j["half_extent_m"][k].is_number()) return absl::DataLossError("half_extent_m is not numbers");
    a.half_extent_m[k] = j["half_extent_m"][k].get<double>();
  }
  absl::StatusOr<std::vector<uint32_t>> body = RowsFromJson(j["body_rows"], scene_gaussians);
  if (!body.ok()) return absl::DataLossError(absl::StrCat("actor ", a.id, ": ", body.status().message()));
  absl::StatusOr<std::vector<uint32_t>> ghost = RowsFromJson(j["ghost_rows"], scene_gaussians);
  if (!ghost.ok()) return absl::DataLossError(absl::StrCat("actor ", a.id, ": ", ghost.status().message()));
  a.body_rows = std::move(*body);
  a.ghost_rows = std::move(*ghost);
  return a;
}

}  // namespace

Eigen::Isometry3d PoseAt(const std::vector<TimedPose>& trajectory, int64_t time_us) {
  if (trajectory.empty()) return Eigen::Isometry3d::Identity();
  if (time_us <= trajectory.front().time_us) return trajectory.front().T_world_from_actor;
  if (time_us >= trajectory.back().time_us) return trajectory.back().T_world_from_actor;
  const auto after = std::upper_bound(trajectory.begin(), trajectory.end(), time_us,
                                      [](int64_t t, const TimedPose& p) { return t < p.time_us; });
  const TimedPose& b = *after;
  const TimedPose& a = *(after - 1);
  const double s = static_cast<double>(time_us - a.time_us) / static_cast<double>(b.time_us - a.time_us);
  const Eigen::Quaterniond qa(a.T_world_from_actor.rotation()), qb(b.T_world_from_actor.rotation());
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = qa.slerp(s, qb).toRotationMatrix();
  T.translation() = (1 - s) * a.T_world_from_actor.translation() + s * b.T_world_from_actor.translation();
  return T;
}

const Actor* ActorSet::Find(int id) const {
  for (const Actor& a : actors) {
    if (a.id == id) return &a;
  }
  return nullptr;
}

absl::StatusOr<uint64_t> SceneChecksum(const std::string& scene_ply_path) {
  std::ifstream in(scene_ply_path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(scene_ply_path, ": cannot be read"));
  std::ostringstream bytes;
  bytes << in.rdbuf();
  const std::string s = bytes.str();
  return checked_file::Checksum(s.data(), s.size());
}

absl::Status WriteActorSet(const ActorSet& set, const std::string& dir) {
  GaussianStore all;
  all.sh_degree = set.sh_degree;
  json actors = json::array();
  for (const Actor& a : set.actors) {
    if (a.gaussians.sh_degree != set.sh_degree || a.gaussians.size() != a.body_rows.size()) {
      return absl::InvalidArgumentError(absl::StrCat("actor ", a.id, ": its Gaussians do not match its body rows"));
    }
    const size_t first = all.size(), n = a.gaussians.size();
    std::vector<uint32_t> rows(n);
    for (size_t i = 0; i < n; ++i) rows[i] = static_cast<uint32_t>(i);
    AppendRows(a.gaussians, rows.data(), n, &all);
    json trajectory = json::array();
    for (const TimedPose& p : a.trajectory) trajectory.push_back(PoseJson(p));
    actors.push_back(json{{"id", a.id},
                          {"track", a.track_id},
                          {"start_time_us", a.start_time_us()},
                          {"end_time_us", a.end_time_us()},
                          {"reference_time_us", a.reference_time_us},
                          {"half_extent_m", {a.half_extent_m.x(), a.half_extent_m.y(), a.half_extent_m.z()}},
                          {"first_gaussian", first},
                          {"num_gaussians", n},
                          {"trajectory", trajectory},
                          {"body_rows", a.body_rows},
                          {"ghost_rows", a.ghost_rows}});
  }
  const json doc{{"schema", kActorSetSchema},
                 {"scene_gaussians", set.scene_gaussians},
                 {"scene_checksum", absl::StrCat(set.scene_checksum)},
                 {"sh_degree", set.sh_degree},
                 {"actors", actors}};
  if (absl::Status s = checked_file::WriteAtomically((fs::path(dir) / kActorsPly).string(), SerializeGaussianPly(all));
      !s.ok()) {
    return s;
  }
  return checked_file::WriteAtomically((fs::path(dir) / kActorsJson).string(), doc.dump(1) + "\n");
}

absl::StatusOr<ActorSet> ReadActorSet(const std::string& dir) {
  const std::string json_path = (fs::path(dir) / kActorsJson).string();
  const std::string ply_path = (fs::path(dir) / kActorsPly).string();
  std::error_code ec;
  if (!fs::exists(json_path, ec)) return absl::NotFoundError(absl::StrCat(json_path, ": the scene has no actors"));
  auto damaged = [&](const std::string& why) {
    return absl::DataLossError(absl::StrCat(json_path, ": ", why, " (extract again: streetsim actors extract)"));
  };
  json doc;
  {
    std::ifstream in(json_path);
    doc = json::parse(in, nullptr, /*allow_exceptions=*/false);
  }
  if (!doc.is_object() || !doc.contains("schema") || !doc["schema"].is_number_integer()) {
    return damaged("not an actor set");
  }
  if (doc["schema"].get<int>() != kActorSetSchema) {
    return damaged(absl::StrCat("schema ", doc["schema"].get<int>(), " is not ", kActorSetSchema));
  }
  if (!doc.contains("scene_gaussians") || !doc["scene_gaussians"].is_number_unsigned() ||
      !doc.contains("scene_checksum") || !doc["scene_checksum"].is_string() || !doc.contains("actors") ||
      !doc["actors"].is_array() || doc["actors"].size() > kMaxActors || !doc.contains("sh_degree") ||
      !doc["sh_degree"].is_number_integer()) {
    return damaged("its header is incomplete");
  }
  ActorSet set;
  set.scene_gaussians = doc["scene_gaussians"].get<size_t>();
  set.sh_degree = doc["sh_degree"].get<int>();
  if (!absl::SimpleAtoi(doc["scene_checksum"].get<std::string>(), &set.scene_checksum)) {
    return damaged("scene_checksum is not a number");
  }
  absl::StatusOr<uint64_t> checksum = SceneChecksum((fs::path(dir) / "scene.ply").string());
  if (!checksum.ok()) return checksum.status();
  if (*checksum != set.scene_checksum) {
    return damaged("it was extracted from another scene.ply (the scene was trained again since)");
  }
  absl::StatusOr<GaussianStore> all = ReadGaussianPly(ply_path);
  if (!all.ok()) return absl::DataLossError(absl::StrCat(ply_path, ": ", all.status().message()));
  if (all->sh_degree != set.sh_degree) return damaged("actors.ply's SH degree is not the set's");
  for (const json& j : doc["actors"]) {
    absl::StatusOr<Actor> a = ActorFromJson(j, set.scene_gaussians);
    if (!a.ok()) return damaged(std::string(a.status().message()));
    if (!j.contains("first_gaussian") || !j["first_gaussian"].is_number_unsigned() || !j.contains("num_gaussians") ||
        !j["num_gaussians"].is_number_unsigned()) {
      return damaged("an actor names no Gaussians");
    }
    const size_t first = j["first_gaussian"].get<size_t>(), n = j["num_gaussians"].get<size_t>();
    if (first > all->size() || n > all->size() - first || n != a->body_rows.size()) {
      return damaged(absl::StrCat("actor ", a->id, ": its Gaussians are not in actors.ply"));
    }
    if (set.Find(a->id) != nullptr) return damaged(absl::StrCat("actor ", a->id, " appears twice"));
    a->gaussians.sh_degree = set.sh_degree;
    std::vector<uint32_t> rows(n);
    for (size_t i = 0; i < n; ++i) rows[i] = static_cast<uint32_t>(first + i);
    AppendRows(*all, rows.data(), n, &a->gaussians);
    set.actors.push_back(std::move(*a));
  }
  return set;
}

}  // namespace streetsim::actors
