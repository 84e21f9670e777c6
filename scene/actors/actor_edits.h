// Edits a scenario makes to a scene's actors (docs/actors.md): remove one, give it a new
// trajectory, or insert a copy of one on a trajectory. Applied to the scene's Gaussians at one
// time: an edited actor's rows (body and the smear training left along its path) leave the scene,
// and its body in its own frame comes back at the edit's pose for that time.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "scene/actors/actor_set.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::actors {

// Bounds on one request's edits (the server's INVALID_ARGUMENT; far above a scenario's needs).
inline constexpr size_t kMaxActorEdits = 64;
inline constexpr size_t kMaxEditPoses = 10000;

struct ActorEdit {
  enum class Kind { kRemove, kMove, kInsert };
  Kind kind = Kind::kRemove;
  int actor_id = 0;                   // kInsert: the actor copied
  std::vector<TimedPose> trajectory;  // kMove, kInsert: strictly increasing times
};

// Checks edits against the set before any work: known actors, at most one remove or move per
// actor, trajectories non-empty with finite, rigid (orthonormal, det +1) poses and increasing
// times, no more than kMaxActorEdits / kMaxEditPoses. INVALID_ARGUMENT naming the edit.
absl::Status ValidateActorEdits(const ActorSet& set, const std::vector<ActorEdit>& edits);

// The Gaussians at time_us with `edits` applied to `at_time` (the scene's Gaussians at that time,
// in scene.ply's rows). Removed rows are dropped, so the rows after them move up; `reflectance`
// (one per row of at_time, or null) is carried along for the LiDAR, copies taking their source
// rows' values. Edits must have passed ValidateActorEdits.
struct EditedScene {
  GaussianStore gaussians;
  std::optional<std::vector<float>> reflectance;
};
EditedScene ApplyActorEdits(const GaussianStore& at_time, const std::vector<float>* reflectance,
                            const ActorSet& set, const std::vector<ActorEdit>& edits, int64_t time_us);

}  // namespace streetsim::actors
