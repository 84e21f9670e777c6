// A LiDAR motion prior for the fine stage (--field-motion-prior W; docs/training.md "Motion prior").
//
// The photometric gradient only reaches a Gaussian whose projection already overlaps the image of
// the surface it should move to; a vehicle fitted by the static stage where it stands longest (the
// KITTI clip's tanker at the light) is metres from where the early frames see it, and the field
// recolours instead of carrying it (docs/field.md "What limits held-out PSNR", session 22). The
// prior gives the field the motion the LiDAR measured: the log's moving objects are followed in
// its scans (scene/init/moving_objects.h, training frames only), and a canonical Gaussian that
// lies on an object's points (within radius_m) at the object's last scan is assigned to it (a
// static stage fits a vehicle where it stands at the end of the log; Gaussians on its earlier
// places are smear, and carried along they would lie over it: measured, docs/training.md; with
// all_scans they are carried all the same, from the latest scan that saw the object there). At a
// view's time t its Δx is pulled towards the object's rigid motion from that scan to t:
//   target_i(t) = M(t) M(t_ref)^-1 μ_i - μ_i,   L = W / N Σ_i huber(|Δx_i - target_i|, huber_m)
// over the N assigned Gaussians. L depends on Δx only, so its gradient enters the field and the
// canonical means only through the field (the trainer adds it to dL/d(deformed means) before the
// field's backward and takes the identity path back out after it).
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string_view>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/log/drive_log.h"
#include "scene/log/kdtree.h"

namespace streetsim::train {

// The weight's bound (the CLI's, the server's and checkpoint.json's): far above any useful value
// (0.3 on KITTI), low enough that the loss stays finite.
inline constexpr double kMaxMotionPriorWeight = 1e4;

struct MotionPriorOptions {
  double weight = 0;                // W; 0: off
  double radius_m = 0.25;           // a Gaussian within this of an object's points is on it
  double huber_m = 0.5;             // quadratic below, linear above: a wrong assignment cannot dominate
  double min_displacement_m = 1.0;  // objects that moved less are left to the photometric loss
  int min_scans = 5;
  // Objects never seen with this many points (far, sparse: cross traffic 20-40 m away at 30-90
  // points) are left out: their registration is loose, and the sweep of a few points along a long
  // path reaches background that does not move.
  int min_object_points = 300;
  // Which of an object's scans assign Gaussians (--field-motion-prior-scans): its last only (the
  // smear on its earlier places is left to the photometric loss), or all of them, each Gaussian
  // carried from the latest scan that saw the object where it lies (the smear moves with the
  // object and lands on it where it stands).
  bool all_scans = false;
  // A preset's prior, not one the user asked for: where the log cannot carry it (too few scans
  // to track objects in), the run goes on without it and says so instead of failing.
  bool optional = false;
};

// MotionPriorOptions::all_scans by name, as the flag, checkpoint.json, train_meta.json and
// TrainingConfig spell it: "last" or "all"; parsing anything else is nullopt.
inline const char* MotionPriorScansName(bool all_scans) { return all_scans ? "all" : "last"; }
inline std::optional<bool> ParseMotionPriorScans(std::string_view name) {
  if (name == "all") return true;
  if (name == "last") return false;
  return std::nullopt;
}

class MotionPrior {
 public:
  // Tracks the log's moving objects (every frame of `log`: pass the training frames' log).
  static absl::StatusOr<std::unique_ptr<MotionPrior>> Build(const DriveLog& log, const MotionPriorOptions& options);

  // Which Gaussians are on which object, from their canonical means [n*3]; call again whenever
  // the rows change (densification, reordering).
  void Assign(const float* means, size_t n, ThreadPool& pool);
  size_t assigned() const { return assigned_; }
  size_t n() const { return track_of_.size(); }
  int num_tracks() const { return static_cast<int>(tracks_.size()); }

  // Adds dL/dΔx at `time_us` to g [n*3] for Δx = deformed - canonical means; returns L.
  double AddGradient(int64_t time_us, const float* means, const float* deformed_means, float* g,
                     ThreadPool& pool) const;
  // The target Δx of Gaussian i at `time_us` (tests); zero when unassigned.
  Eigen::Vector3d TargetDx(size_t i, int64_t time_us, const float* means) const;

  // The object's rigid motion at `time_us` (interpolated between scans, held beyond them).
  struct Track {
    std::vector<int64_t> time_us;
    std::vector<Eigen::Isometry3d> motion;
    Eigen::Isometry3d At(int64_t t) const;
  };
  // For tests: a prior over given tracks and points (points[k] on track point_track[k] at its
  // observation point_obs[k]; without all_scans only the points of each track's last observation
  // are kept).
  static std::unique_ptr<MotionPrior> FromTracks(std::vector<Track> tracks, std::vector<Eigen::Vector3f> points,
                                                 std::vector<int> point_track, std::vector<int> point_obs,
                                                 const MotionPriorOptions& options);

 private:
  MotionPriorOptions options_;
  std::vector<Track> tracks_;
  std::vector<Eigen::Vector3f> points_;
  std::vector<int> point_track_, point_obs_;
  KdTree3 tree_;
  std::vector<int> track_of_, obs_of_;  // per Gaussian; -1: not on an object
  size_t assigned_ = 0;
};

}  // namespace streetsim::train
