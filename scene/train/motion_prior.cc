#include "scene/train/motion_prior.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "scene/init/moving_objects.h"

namespace streetsim::train {
namespace {

// Points searched per Gaussian with all_scans (KdTree3::KNearest's most).
constexpr int kAllScansNeighbours = 32;

}  // namespace

Eigen::Isometry3d MotionPrior::Track::At(int64_t t) const {
  if (t <= time_us.front()) return motion.front();
  if (t >= time_us.back()) return motion.back();
  const size_t k = std::upper_bound(time_us.begin(), time_us.end(), t) - time_us.begin() - 1;
  const double a = double(t - time_us[k]) / double(time_us[k + 1] - time_us[k]);
  const Eigen::Quaterniond q0(motion[k].linear()), q1(motion[k + 1].linear());
  Eigen::Isometry3d m = Eigen::Isometry3d::Identity();
  m.linear() = q0.slerp(a, q1).toRotationMatrix();
  m.translation() = (1 - a) * motion[k].translation() + a * motion[k + 1].translation();
  return m;
}

absl::StatusOr<std::unique_ptr<MotionPrior>> MotionPrior::Build(const DriveLog& log,
                                                                const MotionPriorOptions& options) {
  if (!(options.weight > 0 && options.weight <= 1e4) || !(options.radius_m > 0 && options.radius_m <= 5) ||
      !(options.huber_m > 0 && options.huber_m <= 100)) {
    return absl::InvalidArgumentError("motion prior: weight in (0, 1e4], radius in (0, 5] m, huber in (0, 100] m");
  }
  MovingObjectOptions mo;
  mo.keep_points = true;
  absl::StatusOr<MovingObjects> objects = TrackMovingObjects(log, mo);
  if (!objects.ok()) return objects.status();
  std::vector<Track> tracks;
  std::vector<Eigen::Vector3f> points;
  std::vector<int> point_track, point_obs;
  for (const MovingObjectTrack& t : objects->tracks) {
    if (static_cast<int>(t.observations.size()) < options.min_scans ||
        t.NetDisplacementM() < options.min_displacement_m) {
      continue;
    }
    int most_points = 0;
    for (const ObjectObservation& ob : t.observations) most_points = std::max(most_points, ob.num_points);
    if (most_points < options.min_object_points) continue;
    const int id = static_cast<int>(tracks.size());
    Track track;
    for (size_t k = 0; k < t.observations.size(); ++k) {
      const ObjectObservation& ob = t.observations[k];
      track.time_us.push_back(ob.time_us);
      track.motion.push_back(ob.T_world_motion);
      for (const Eigen::Vector3f& p : ob.points_world) {
        points.push_back(p);
        point_track.push_back(id);
        point_obs.push_back(static_cast<int>(k));
      }
    }
    tracks.push_back(std::move(track));
  }
  return FromTracks(std::move(tracks), std::move(points), std::move(point_track), std::move(point_obs), options);
}

std::unique_ptr<MotionPrior> MotionPrior::FromTracks(std::vector<Track> tracks, std::vector<Eigen::Vector3f> points,
                                                     std::vector<int> point_track, std::vector<int> point_obs,
                                                     const MotionPriorOptions& options) {
  auto p = std::unique_ptr<MotionPrior>(new MotionPrior());
  p->options_ = options;
  p->tracks_ = std::move(tracks);
  // Without all_scans only where each track ends is a Gaussian assigned (Assign), so only those
  // points are searched.
  for (size_t k = 0; k < points.size(); ++k) {
    const bool last = point_obs[k] + 1 == static_cast<int>(p->tracks_[point_track[k]].time_us.size());
    if (!last && !options.all_scans) continue;
    p->points_.push_back(points[k]);
    p->point_track_.push_back(point_track[k]);
    p->point_obs_.push_back(point_obs[k]);
  }
  p->tree_.Build(&p->points_);
  return p;
}

void MotionPrior::Assign(const float* means, size_t n, ThreadPool& pool) {
  track_of_.assign(n, -1);
  obs_of_.assign(n, -1);
  const float r2 = static_cast<float>(options_.radius_m * options_.radius_m);
  pool.ParallelFor(static_cast<int64_t>(n), 4096, [&](int64_t begin, int64_t end, int) {
    int near[kAllScansNeighbours];
    float near_d2[kAllScansNeighbours];
    for (int64_t i = begin; i < end; ++i) {
      if (options_.all_scans) {
        // The latest scan among the nearest points within the radius: where an object stood for
        // many scans their points coincide and any of them gives the same motion; where it passed,
        // each scan leaves a few points here, all among the nearest.
        const int found = tree_.KNearest(Eigen::Vector3f(means[i * 3], means[i * 3 + 1], means[i * 3 + 2]),
                                         kAllScansNeighbours, r2, near, near_d2);
        int64_t latest_us = std::numeric_limits<int64_t>::min();
        for (int j = 0; j < found; ++j) {
          const int k = near[j];
          const int64_t t_us = tracks_[point_track_[k]].time_us[point_obs_[k]];
          if (t_us > latest_us) {
            latest_us = t_us;
            track_of_[i] = point_track_[k];
            obs_of_[i] = point_obs_[k];
          }
        }
        continue;
      }
      // On an object where its track ends (the nearest such point; the tree holds no other): a
      // static stage fits a vehicle where it stands at the end of the log, and the Gaussians it
      // left on the vehicle's earlier places are a smear that, carried along, would lie over it.
      const int k = tree_.Nearest(Eigen::Vector3f(means[i * 3], means[i * 3 + 1], means[i * 3 + 2]), r2);
      if (k < 0) continue;
      track_of_[i] = point_track_[k];
      obs_of_[i] = point_obs_[k];
    }
  });
  assigned_ = static_cast<size_t>(std::count_if(track_of_.begin(), track_of_.end(), [](int t) { return t >= 0; }));
}

Eigen::Vector3d MotionPrior::TargetDx(size_t i, int64_t time_us, const float* means) const {
  if (i >= track_of_.size() || track_of_[i] < 0) return Eigen::Vector3d::Zero();
  const Track& t = tracks_[track_of_[i]];
  const Eigen::Vector3d mu(means[i * 3], means[i * 3 + 1], means[i * 3 + 2]);
  return t.At(time_us) * (t.motion[obs_of_[i]].inverse() * mu) - mu;
}

double MotionPrior::AddGradient(int64_t time_us, const float* means, const float* deformed_means, float* g,
                                ThreadPool& pool) const {
  if (assigned_ == 0) return 0;
  const double scale = options_.weight / static_cast<double>(assigned_);
  const double delta = options_.huber_m;
  // The target motion per track once: t.At(time) M(t_ref)^-1 for every (track, observation).
  std::vector<std::vector<Eigen::Isometry3d>> carry(tracks_.size());
  for (size_t t = 0; t < tracks_.size(); ++t) {
    const Eigen::Isometry3d now = tracks_[t].At(time_us);
    for (const Eigen::Isometry3d& m : tracks_[t].motion) carry[t].push_back(now * m.inverse());
  }
  std::vector<double> partial(static_cast<size_t>(pool.num_threads()), 0.0);
  pool.ParallelFor(static_cast<int64_t>(track_of_.size()), 8192, [&](int64_t begin, int64_t end, int worker) {
    double sum = 0;
    for (int64_t i = begin; i < end; ++i) {
      if (track_of_[i] < 0) continue;
      const Eigen::Vector3d mu(means[i * 3], means[i * 3 + 1], means[i * 3 + 2]);
      const Eigen::Vector3d dx(deformed_means[i * 3] - means[i * 3], deformed_means[i * 3 + 1] - means[i * 3 + 1],
                               deformed_means[i * 3 + 2] - means[i * 3 + 2]);
      const Eigen::Vector3d target = carry[track_of_[i]][obs_of_[i]] * mu - mu;
      const Eigen::Vector3d e = dx - target;
      const double r = e.norm();
      sum += r <= delta ? 0.5 * r * r : delta * (r - 0.5 * delta);
      const Eigen::Vector3d grad = scale * (r <= delta ? e : Eigen::Vector3d(e * (delta / r)));
      for (int c = 0; c < 3; ++c) g[i * 3 + c] += static_cast<float>(grad[c]);
    }
    partial[static_cast<size_t>(worker)] += sum;
  });
  double total = 0;
  for (double s : partial) total += s;
  return scale * total;
}

}  // namespace streetsim::train
