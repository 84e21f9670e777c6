// Actors from a trained scene and its log's LiDAR, without boxes or labels (docs/actors.md).
//
// Each object the LiDAR followed (scene/init/moving_objects.h) that moved, was seen often and
// closely enough becomes an actor:
//  - its frame: every scan's points carried by the track's motion onto the scan that saw it with
//    the most points (the reference), the box about them (2nd..98th percentile, heading from the
//    points' principal horizontal axis, signed along the track's motion, reaching down towards
//    the ground the tracker cut off but not into it);
//  - its trajectory: the box's pose at each scan, T(o) = M(o) M(ref)^-1 T(ref);
//  - its body: the Gaussians inside the box at the reference time (the scene deformed to that
//    time when it has a field), kept in the actor frame;
//  - its ghost: the Gaussians inside the box at every other scan's time that are not its body:
//    what training left along the path (a static model smears a vehicle over every place it
//    stood). The box sweeps through space the vehicle drove through, so that is free space.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/actors/actor_set.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/init/moving_objects.h"

namespace streetsim::actors {

struct ActorExtractionOptions {
  int min_scans = 5;                // tracks seen in fewer scans are too loose to be actors
  double min_displacement_m = 1.0;  // objects that moved less are left in the scene
  int min_object_points = 300;      // never seen this close: its box would be a guess
  double box_margin_m = 0.15;       // around the points (not below), for Gaussians just outside them
  // Below the lowest point the box reaches this far: the tracker drops points under 0.3 m above
  // the ground (wheels, sills), and the road beneath the path must stay (0.15 m of clearance).
  double ground_reach_m = 0.15;
};

// The scene's Gaussians at a time, in scene.ply's rows (a dynamic scene deformed to that time; a
// static scene's own Gaussians for every time).
using GaussiansAt = std::function<absl::StatusOr<const GaussianStore*>(int64_t time_us)>;

// Actors for `tracks` (with points kept: MovingObjectOptions::keep_points). Tracks that fail the
// options' filters are skipped; a Gaussian belongs to at most one actor (the first that claims it).
// The set's scene_checksum is left for the caller.
absl::StatusOr<ActorSet> ExtractActors(const std::vector<MovingObjectTrack>& tracks, const GaussiansAt& at,
                                       const ActorExtractionOptions& options);

}  // namespace streetsim::actors
