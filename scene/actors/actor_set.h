// A trained scene's actors (docs/actors.md): the objects its log's LiDAR followed, each with its
// Gaussians in its own frame, its timed poses over the log, an oriented box and a time range.
//
// Beside the scene: DIR/actors.json (schema 1: the actors, their trajectories and which rows of
// scene.ply they own) and DIR/actors.ply (every actor's Gaussians in its own frame, actor after
// actor). Both are tied to scene.ply by its Gaussian count and checksum: a scene retrained after
// its actors were extracted is refused by name, never edited with another scene's rows.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::actors {

inline constexpr int kActorSetSchema = 1;
inline constexpr char kActorsJson[] = "actors.json";
inline constexpr char kActorsPly[] = "actors.ply";

struct TimedPose {
  int64_t time_us = 0;
  Eigen::Isometry3d T_world_from_actor = Eigen::Isometry3d::Identity();
};

// The pose at time_us on a trajectory of increasing times: translation interpolated linearly and
// rotation by slerp between the two poses around it; before the first pose and after the last the
// actor stands at that pose.
Eigen::Isometry3d PoseAt(const std::vector<TimedPose>& trajectory, int64_t time_us);

struct Actor {
  int id = 0;                       // 1, 2, ... within the set (the API's actor_id)
  int track_id = 0;                 // the LiDAR track it came from (scene/init/moving_objects.h)
  std::vector<TimedPose> trajectory;  // the log's: one pose per scan that saw it
  Eigen::Vector3d half_extent_m = Eigen::Vector3d::Zero();  // box about the actor frame's origin; x forward, z up
  // Rows of scene.ply: the actor's body (in the order of its Gaussians in actors.ply) and what
  // training left along its path (smear that must go when the actor is removed or moved).
  std::vector<uint32_t> body_rows;
  std::vector<uint32_t> ghost_rows;
  GaussianStore gaussians;  // the body in the actor frame, at the scan that saw it best
  int64_t reference_time_us = 0;

  int64_t start_time_us() const { return trajectory.empty() ? 0 : trajectory.front().time_us; }
  int64_t end_time_us() const { return trajectory.empty() ? 0 : trajectory.back().time_us; }
};

struct ActorSet {
  size_t scene_gaussians = 0;  // scene.ply's count and checksum when extracted
  uint64_t scene_checksum = 0;
  int sh_degree = 0;
  std::vector<Actor> actors;

  const Actor* Find(int id) const;
};

// The checksum ActorSet::scene_checksum holds: scene.ply's bytes (checked_file::Checksum).
absl::StatusOr<uint64_t> SceneChecksum(const std::string& scene_ply_path);

// Writes DIR/actors.json and DIR/actors.ply atomically (the PLY first: a reader that finds the
// JSON finds its Gaussians).
absl::Status WriteActorSet(const ActorSet& set, const std::string& dir);

// Reads DIR's actor set; NOT_FOUND when the scene has none, DATA_LOSS naming the file when it is
// damaged, from a newer schema, or not of this scene.ply.
absl::StatusOr<ActorSet> ReadActorSet(const std::string& dir);

}  // namespace streetsim::actors
