// A `streetsim replay` scenario (docs/server.md "Replay", docs/actors.md "Scenarios"): the JSON
// file read into typed values, each field checked for its type and range before the server is
// reached (a wrong type is exit 2 naming the field, never an exception); the ego's pose per step
// and the actor edits resolved against the scene.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "absl/status/statusor.h"
#include "streetsim/v1/scene.pb.h"

namespace streetsim {

struct ReplayScenario {
  std::optional<std::string> server;  // HOST:PORT (--server wins)
  std::string scene;
  int num_steps = 0;                 // 1..100000
  int64_t step_dt_us = 100000;       // > 0
  int64_t start_time_us = 0;         // 0: the scene's start
  uint64_t seed = 0;
  bool jpeg = false, depth = false;
  std::vector<std::string> sensors;  // empty: every camera of the rig
  int width = 0, height = 0;         // 0: the sensor's own
  std::optional<double> video_fps;   // unset: real time
  nlohmann::json ego;                // {"mode": "log" | "poses" | "straight", ...}; checked by ScenarioEgoPoses
  nlohmann::json actors;             // null, or the edits ScenarioActorEdits reads
};

// InvalidArgument naming the file or the field for a missing, huge, non-JSON or ill-typed file.
absl::StatusOr<ReplayScenario> ReadReplayScenario(const std::string& path);

// The ego's pose at each of the scenario's steps, from step time t0.
absl::StatusOr<std::vector<Eigen::Isometry3d>> ScenarioEgoPoses(const ReplayScenario& scenario,
                                                                const v1::Scene& scene, int64_t t0);

// An actor edit of the scenario and the step it starts at.
struct ScenarioEdit {
  int from_step = 0;
  v1::ActorEdit edit;
};
// The scenario's actor edits (docs/actors.md "Scenarios") against the scene's actors: each
// {"edit": "remove"|"move"|"insert", "actor_id": N, "from_step": K (0), "path": [...]}. A path pose
// is either {"step": K, "ego_xyz_m": [x, y, z], "yaw_deg": Y} (in the frame of the replay's ego at
// step K, `ego`: "15 m ahead, one lane left"; z defaults to the height the log had the actor at
// above the ego) or {"time_us": T, "T_world_from_actor": [16 numbers]}. Steps are at t0 + k dt.
absl::StatusOr<std::vector<ScenarioEdit>> ScenarioActorEdits(const nlohmann::json& list, const v1::Scene& scene,
                                                            const std::vector<Eigen::Isometry3d>& ego, int64_t t0,
                                                            int64_t dt);

}  // namespace streetsim
