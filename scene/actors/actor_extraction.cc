#include "scene/actors/actor_extraction.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <utility>

#include <Eigen/Eigenvalues>

#include "absl/strings/str_cat.h"
#include "scene/actors/rigid_gaussians.h"

namespace streetsim::actors {
namespace {

bool Qualifies(const MovingObjectTrack& t, const ActorExtractionOptions& o) {
  if (static_cast<int>(t.observations.size()) < o.min_scans || t.NetDisplacementM() < o.min_displacement_m) {
    return false;
  }
  int most = 0;
  for (const ObjectObservation& ob : t.observations) most = std::max(most, ob.num_points);
  return most >= o.min_object_points;
}

double Percentile(std::vector<double> v, double q) {
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size() - 1) + 0.5));
  std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
  return v[k];
}

struct Box {
  Eigen::Isometry3d T_world_from_actor = Eigen::Isometry3d::Identity();  // at the reference scan
  Eigen::Vector3d half_extent_m = Eigen::Vector3d::Zero();
};

// The box about a track's points gathered onto its reference scan (world frame, z up); x points
// along `motion` (the heading of a principal axis is only defined up to its sign).
Box FitBox(const std::vector<Eigen::Vector3d>& points, const Eigen::Vector3d& motion, const ActorExtractionOptions& o) {
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  for (const Eigen::Vector3d& p : points) mean += p.head<2>();
  mean /= static_cast<double>(points.size());
  Eigen::Matrix2d cov = Eigen::Matrix2d::Zero();
  for (const Eigen::Vector3d& p : points) {
    const Eigen::Vector2d d = p.head<2>() - mean;
    cov += d * d.transpose();
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(cov);
  Eigen::Vector2d forward = eig.eigenvectors().col(1);  // the largest eigenvalue's
  if (forward.dot(motion.head<2>()) < 0) forward = -forward;
  const double yaw = std::atan2(forward.y(), forward.x());
  const Eigen::Matrix3d R = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  std::vector<double> axis[3];
  for (const Eigen::Vector3d& p : points) {
    const Eigen::Vector3d local = R.transpose() * p;
    for (int a = 0; a < 3; ++a) axis[a].push_back(local[a]);
  }
  Eigen::Vector3d lo, hi;
  for (int a = 0; a < 3; ++a) {
    lo[a] = Percentile(axis[a], 0.02) - (a == 2 ? o.ground_reach_m : o.box_margin_m);
    hi[a] = Percentile(axis[a], 0.98) + o.box_margin_m;
  }
  Box box;
  box.half_extent_m = (hi - lo) / 2;
  box.T_world_from_actor.linear() = R;
  box.T_world_from_actor.translation() = R * ((lo + hi) / 2);
  return box;
}

// Rows of `g` whose means lie in the box at pose T.
std::vector<uint32_t> RowsInBox(const GaussianStore& g, const Eigen::Isometry3d& T_world_from_actor,
                                const Eigen::Vector3d& half_extent_m) {
  const Eigen::Isometry3d T_actor_from_world = T_world_from_actor.inverse();
  std::vector<uint32_t> rows;
  for (size_t i = 0; i < g.size(); ++i) {
    const Eigen::Vector3d p = T_actor_from_world * Eigen::Vector3d(g.means[i * 3], g.means[i * 3 + 1], g.means[i * 3 + 2]);
    if ((p.cwiseAbs() - half_extent_m).maxCoeff() <= 0) rows.push_back(static_cast<uint32_t>(i));
  }
  return rows;
}

// Below this share of followers the field is taken not to carry the actor at all.
constexpr double kMinFollowingShare = 0.2;

// Which of the Gaussians in the box at the reference scan move with the actor: compared at the
// scan where the actor is farthest from there, a body Gaussian is where the actor's motion carries
// it (within half that distance, at most 0.5 m), and smear the static stage left at the reference
// place has stayed. A scene without a field moves nothing, and a field may not carry the actor
// (under kMinFollowingShare of them follow): all of them are the body then (the best a static
// model has).
absl::StatusOr<std::vector<uint8_t>> FollowsTheActor(const MovingObjectTrack& track, size_t ref, const std::vector<TimedPose>& poses,
                                     const std::vector<uint32_t>& rows, const GaussianStore& at_ref,
                                     const GaussiansAt& at) {
  size_t far = ref;
  double far_m = 0;
  for (size_t k = 0; k < poses.size(); ++k) {
    const double d = (poses[k].T_world_from_actor.translation() - poses[ref].T_world_from_actor.translation()).norm();
    if (d > far_m) {
      far_m = d;
      far = k;
    }
  }
  std::vector<uint8_t> follows(rows.size(), 1);
  if (far == ref || rows.empty()) return follows;
  absl::StatusOr<const GaussianStore*> g = at(track.observations[far].time_us);
  if (!g.ok()) return g.status();
  const Eigen::Isometry3d carry =
      poses[far].T_world_from_actor * poses[ref].T_world_from_actor.inverse();
  const double tolerance_m = std::min(0.5, far_m / 2);
  bool any_moved = false;
  for (size_t j = 0; j < rows.size(); ++j) {
    const Eigen::Vector3d was(at_ref.means[j * 3], at_ref.means[j * 3 + 1], at_ref.means[j * 3 + 2]);
    const float* m = &(*g)->means[rows[j] * 3];
    const Eigen::Vector3d now(m[0], m[1], m[2]);
    any_moved = any_moved || (now - was).norm() > 1e-3;
    follows[j] = (now - carry * was).norm() <= tolerance_m;
  }
  // A field that does not carry this actor (it recolours instead, or moves nothing): what stands
  // in the box at the reference scan is all the body there is, as in a static scene.
  const size_t following = static_cast<size_t>(std::count(follows.begin(), follows.end(), 1));
  if (!any_moved || following < kMinFollowingShare * static_cast<double>(rows.size())) {
    std::fill(follows.begin(), follows.end(), 1);
  }
  return follows;
}

// A qualifying track's reference scan, box and trajectory: they come from its points alone.
struct TrackFit {
  const MovingObjectTrack* track = nullptr;
  size_t ref = 0;
  Box box;
  std::vector<TimedPose> trajectory;
};

absl::StatusOr<TrackFit> FitTrack(const MovingObjectTrack& track, const ActorExtractionOptions& options) {
  TrackFit fit;
  fit.track = &track;
  for (size_t k = 0; k < track.observations.size(); ++k) {
    if (track.observations[k].num_points > track.observations[fit.ref].num_points) fit.ref = k;
  }
  const Eigen::Isometry3d M_ref = track.observations[fit.ref].T_world_motion;
  std::vector<Eigen::Vector3d> points;
  for (const ObjectObservation& ob : track.observations) {
    const Eigen::Isometry3d to_ref = M_ref * ob.T_world_motion.inverse();
    for (const Eigen::Vector3f& p : ob.points_world) points.push_back(to_ref * p.cast<double>());
  }
  if (points.size() < 10) {
    return absl::InvalidArgumentError(
        absl::StrCat("track ", track.id, " kept no points (MovingObjectOptions::keep_points)"));
  }
  const Eigen::Vector3d motion = track.ReferencePoint(track.observations.size() - 1) - track.ReferencePoint(0);
  fit.box = FitBox(points, motion, options);
  for (const ObjectObservation& ob : track.observations) {
    fit.trajectory.push_back({ob.time_us, ob.T_world_motion * M_ref.inverse() * fit.box.T_world_from_actor});
  }
  return fit;
}

// Per fit, the rows inside its box at any of its scans but the reference one (its ghost before
// the claims of earlier actors are taken out). One pass over the scans' distinct times, so each
// time's scene is deformed once for every track: asked per track and scan, the deformations were
// most of an extraction (13 minutes on a 558k-Gaussian KITTI scene with 10 actors).
absl::StatusOr<std::vector<std::vector<uint8_t>>> GhostCandidates(const std::vector<TrackFit>& fits,
                                                                   const GaussiansAt& at) {
  std::map<int64_t, std::vector<std::pair<size_t, size_t>>> by_time;  // time -> (fit, scan)
  for (size_t f = 0; f < fits.size(); ++f) {
    for (size_t k = 0; k < fits[f].trajectory.size(); ++k) {
      if (k != fits[f].ref) by_time[fits[f].trajectory[k].time_us].push_back({f, k});
    }
  }
  std::vector<std::vector<uint8_t>> candidates(fits.size());
  for (const auto& [time_us, scans] : by_time) {
    absl::StatusOr<const GaussianStore*> g = at(time_us);
    if (!g.ok()) return g.status();
    for (const auto& [f, k] : scans) {
      std::vector<uint8_t>& c = candidates[f];
      if (c.empty()) c.assign((*g)->size(), 0);
      if (c.size() != (*g)->size()) return absl::InternalError("the scene's Gaussian count changed between times");
      for (uint32_t r : RowsInBox(**g, fits[f].trajectory[k].T_world_from_actor, fits[f].box.half_extent_m)) c[r] = 1;
    }
  }
  return candidates;
}

}  // namespace

absl::StatusOr<ActorSet> ExtractActors(const std::vector<MovingObjectTrack>& tracks, const GaussiansAt& at,
                                       const ActorExtractionOptions& options) {
  std::vector<TrackFit> fits;
  for (const MovingObjectTrack& track : tracks) {
    if (!Qualifies(track, options)) continue;
    absl::StatusOr<TrackFit> fit = FitTrack(track, options);
    if (!fit.ok()) return fit.status();
    fits.push_back(*std::move(fit));
  }
  absl::StatusOr<std::vector<std::vector<uint8_t>>> ghost_candidates = GhostCandidates(fits, at);
  if (!ghost_candidates.ok()) return ghost_candidates.status();
  ActorSet set;
  std::vector<uint8_t> claimed;
  for (size_t f = 0; f < fits.size(); ++f) {
    const TrackFit& fit = fits[f];
    const MovingObjectTrack& track = *fit.track;
    const Box& box = fit.box;
    Actor actor;
    actor.id = static_cast<int>(set.actors.size()) + 1;
    actor.track_id = track.id;
    actor.half_extent_m = box.half_extent_m;
    actor.reference_time_us = track.observations[fit.ref].time_us;
    actor.trajectory = fit.trajectory;
    absl::StatusOr<const GaussianStore*> at_ref = at(actor.reference_time_us);
    if (!at_ref.ok()) return at_ref.status();
    const GaussianStore& g_ref = **at_ref;
    if (set.actors.empty() && claimed.empty()) {
      set.scene_gaussians = g_ref.size();
      set.sh_degree = g_ref.sh_degree;
      claimed.assign(g_ref.size(), 0);
    }
    if (g_ref.size() != set.scene_gaussians) {
      return absl::InternalError("the scene's Gaussian count changed between times");
    }
    std::vector<uint32_t> in_box;
    for (uint32_t r : RowsInBox(g_ref, box.T_world_from_actor, box.half_extent_m)) {
      if (!claimed[r]) in_box.push_back(r);
    }
    // Their positions now: `at` may reuse g_ref's storage for the next time it is asked.
    GaussianStore in_box_ref;
    in_box_ref.sh_degree = g_ref.sh_degree;
    AppendRows(g_ref, in_box.data(), in_box.size(), &in_box_ref);
    absl::StatusOr<std::vector<uint8_t>> follows =
        FollowsTheActor(track, fit.ref, actor.trajectory, in_box, in_box_ref, at);
    if (!follows.ok()) return follows.status();
    std::vector<uint32_t> body_index;  // into in_box
    for (size_t j = 0; j < in_box.size(); ++j) {
      claimed[in_box[j]] = 1;
      if ((*follows)[j]) {
        actor.body_rows.push_back(in_box[j]);
        body_index.push_back(static_cast<uint32_t>(j));
      } else {
        actor.ghost_rows.push_back(in_box[j]);
      }
    }
    // The body in its own frame: the reference time's Gaussians carried back by the box's pose.
    actor.gaussians.sh_degree = g_ref.sh_degree;
    AppendRows(in_box_ref, body_index.data(), body_index.size(), &actor.gaussians);
    TransformGaussians(box.T_world_from_actor.inverse(), &actor.gaussians);
    const std::vector<uint8_t>& ghost = (*ghost_candidates)[f];  // empty: seen at its reference scan only
    if (!ghost.empty() && ghost.size() != set.scene_gaussians) {
      return absl::InternalError("the scene's Gaussian count changed between times");
    }
    for (size_t r = 0; r < ghost.size(); ++r) {
      if (!ghost[r] || claimed[r]) continue;
      claimed[r] = 1;
      actor.ghost_rows.push_back(static_cast<uint32_t>(r));
    }
    std::sort(actor.ghost_rows.begin(), actor.ghost_rows.end());
    set.actors.push_back(std::move(actor));
  }
  return set;
}

}  // namespace streetsim::actors
