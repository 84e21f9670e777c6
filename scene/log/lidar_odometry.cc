#include "scene/log/lidar_odometry.h"

#include <chrono>
#include <cmath>
#include <memory>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>

#include "absl/strings/str_cat.h"
#include "scene/log/point_scatter.h"
#include "scene/log/voxel_hash.h"

namespace streetsim {
namespace {

Eigen::Isometry3d ExpSe3(const Eigen::Matrix<double, 6, 1>& xi) {
  // xi = (omega, v); first-order translation is enough for the small GN increments.
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  const double angle = xi.head<3>().norm();
  if (angle > 1e-12) t.linear() = Eigen::AngleAxisd(angle, xi.head<3>() / angle).toRotationMatrix();
  t.translation() = xi.tail<3>();
  return t;
}

double RotationAngleDeg(const Eigen::Matrix3d& r) {
  return Eigen::AngleAxisd(r).angle() * 180.0 / M_PI;
}

}  // namespace

std::vector<Eigen::Vector3f> RangeFilter(const std::vector<Eigen::Vector3f>& scan, double min_range_m,
                                         double max_range_m) {
  std::vector<Eigen::Vector3f> out;
  out.reserve(scan.size());
  const float lo = static_cast<float>(min_range_m * min_range_m);
  const float hi = static_cast<float>(max_range_m * max_range_m);
  for (const Eigen::Vector3f& p : scan) {
    const float r2 = p.squaredNorm();
    if (r2 >= lo && r2 <= hi) out.push_back(p);
  }
  return out;
}

void BuildPlaneCloud(const std::vector<Eigen::Vector3f>& points, const LidarOdometryOptions& options,
                     PlaneCloud* cloud) {
  std::vector<Eigen::Vector3f> sampled = VoxelDownsample(points, options.target_voxel_m);
  KdTree3 tree(&sampled);
  cloud->points.clear();
  cloud->normals.clear();
  const int k = options.normal_neighbours;
  int idx[32];
  float d2[32];
  const float radius_sq = static_cast<float>(std::pow(8 * options.target_voxel_m, 2));
  for (size_t i = 0; i < sampled.size(); ++i) {
    const int found = tree.KNearest(sampled[i], k, radius_sq, idx, d2);
    if (found < 5) continue;
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> eig(NeighbourScatter(sampled, idx, found));
    const Eigen::Vector3d ev = eig.eigenvalues();  // ascending
    const double sum = ev.sum();
    if (sum <= 0 || ev[0] / sum > options.max_planarity) continue;
    cloud->points.push_back(sampled[i]);
    cloud->normals.push_back(eig.eigenvectors().col(0).normalized().cast<float>());
  }
  cloud->tree.Build(&cloud->points);
}

IcpResult PointToPlaneIcp(const PlaneCloud& target, const std::vector<Eigen::Vector3f>& source,
                          const Eigen::Isometry3d& initial, const LidarOdometryOptions& options) {
  IcpResult result;
  Eigen::Isometry3d t = initial;
  const int iters = std::max(1, options.max_iterations);
  for (int it = 0; it < iters; ++it) {
    // The radius shrinks over the first half, then stays: wide enough to catch the initial guess's
    // error, tight enough at the end to ignore moving objects.
    const double frac = std::min(1.0, it / (0.5 * iters));
    const double radius = options.initial_correspondence_m +
                          frac * (options.final_correspondence_m - options.initial_correspondence_m);
    const float radius_sq = static_cast<float>(radius * radius);
    Eigen::Matrix<double, 6, 6> h = Eigen::Matrix<double, 6, 6>::Zero();
    Eigen::Matrix<double, 6, 1> g = Eigen::Matrix<double, 6, 1>::Zero();
    double sq = 0;
    int inliers = 0;
    const Eigen::Matrix3f r = t.linear().cast<float>();
    const Eigen::Vector3f tr = t.translation().cast<float>();
    for (const Eigen::Vector3f& p : source) {
      const Eigen::Vector3f q = r * p + tr;
      const int nn = target.tree.Nearest(q, radius_sq);
      if (nn < 0) continue;
      const Eigen::Vector3d n = target.normals[nn].cast<double>();
      const Eigen::Vector3d qd = q.cast<double>();
      const double res = n.dot(qd - target.points[nn].cast<double>());
      Eigen::Matrix<double, 6, 1> j;
      j.head<3>() = qd.cross(n);
      j.tail<3>() = n;
      const double w = std::abs(res) <= options.huber_m ? 1.0 : options.huber_m / std::abs(res);
      h.noalias() += w * j * j.transpose();
      g.noalias() += w * res * j;
      sq += res * res;
      ++inliers;
    }
    result.iterations = it + 1;
    result.inliers = inliers;
    result.rmse_m = inliers > 0 ? std::sqrt(sq / inliers) : 0;
    if (inliers < 50) break;
    const Eigen::Matrix<double, 6, 1> xi = h.ldlt().solve(-g);
    if (!xi.allFinite()) break;
    t = ExpSe3(xi) * t;
    if (xi.head<3>().norm() < 1e-6 && xi.tail<3>().norm() < 1e-5 && frac >= 1.0) {
      result.converged = true;
      break;
    }
  }
  t.linear() = Eigen::Quaterniond(t.linear()).normalized().toRotationMatrix();
  result.T_target_from_source = t;
  return result;
}

absl::StatusOr<LidarOdometryResult> RunLidarOdometry(const DriveLog& log,
                                                     const LidarOdometryOptions& options) {
  if (log.lidars.empty()) return absl::FailedPreconditionError(absl::StrCat(log.root, ": log has no LiDAR"));
  const int n = static_cast<int>(log.frames.size());
  const int first = std::max(0, options.first_frame);
  const int last = options.last_frame < 0 ? n : std::min(n, options.last_frame);
  if (last - first < 2) {
    return absl::InvalidArgumentError(absl::StrCat("LiDAR odometry needs at least 2 frames, got ", last - first));
  }
  const Eigen::Isometry3d T_ego_from_lidar = log.lidars[0].T_ego_from_lidar;
  const Eigen::Isometry3d T_lidar_from_ego = T_ego_from_lidar.inverse();

  LidarOdometryResult out;
  const auto start = std::chrono::steady_clock::now();
  auto target = std::make_unique<PlaneCloud>();
  bool have_target = false;
  Eigen::Isometry3d T_world_from_lidar = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d velocity = Eigen::Isometry3d::Identity();  // T_prev_from_cur of the last step
  for (int f = first; f < last; ++f) {
    const LidarObservation* obs = nullptr;
    for (const LidarObservation& o : log.frames[f].lidars) {
      if (o.lidar == 0) obs = &o;
    }
    std::vector<Eigen::Vector3f> points;
    if (obs != nullptr) {
      absl::StatusOr<LidarScan> scan = LoadLidarScan(obs->path);
      if (!scan.ok()) return scan.status();
      points = RangeFilter(scan->points, options.min_range_m, options.max_range_m);
    }
    IcpResult icp;
    if (points.size() < 100) {
      out.problems.push_back(absl::StrCat("frame ", log.frames[f].source_index,
                                          ": no usable LiDAR scan; constant velocity assumed"));
      if (have_target) T_world_from_lidar = T_world_from_lidar * velocity;
    } else {
      if (have_target) {
        const std::vector<Eigen::Vector3f> source = VoxelDownsample(points, options.source_voxel_m);
        icp = PointToPlaneIcp(*target, source, velocity, options);
        if (icp.inliers < 100) {
          out.problems.push_back(absl::StrCat("frame ", log.frames[f].source_index, ": ICP found ",
                                              icp.inliers, " correspondences; constant velocity assumed"));
          icp.T_target_from_source = velocity;
        }
        velocity = icp.T_target_from_source;
        T_world_from_lidar = T_world_from_lidar * velocity;
      }
      auto next = std::make_unique<PlaneCloud>();
      BuildPlaneCloud(points, options, next.get());
      target = std::move(next);
      have_target = true;
    }
    out.frames.push_back(f);
    out.icp.push_back(icp);
    out.T_world_from_ego.push_back(T_ego_from_lidar * T_world_from_lidar * T_lidar_from_ego);
  }
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  out.ms_per_scan = ms / out.frames.size();
  return out;
}

TrajectoryComparison CompareTrajectories(const std::vector<Eigen::Isometry3d>& estimate,
                                         const std::vector<Eigen::Isometry3d>& reference) {
  TrajectoryComparison c;
  const size_t n = std::min(estimate.size(), reference.size());
  if (n < 2) return c;
  const Eigen::Isometry3d e0 = estimate[0].inverse(), r0 = reference[0].inverse();
  double rel_t = 0, rel_r = 0;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Isometry3d e = e0 * estimate[i], r = r0 * reference[i];
    const double err = (e.translation() - r.translation()).norm();
    c.max_translation_error_m = std::max(c.max_translation_error_m, err);
    if (i + 1 == n) {
      c.final_translation_error_m = err;
      c.final_rotation_error_deg = RotationAngleDeg(e.linear().transpose() * r.linear());
    }
    if (i > 0) {
      c.reference_distance_m += (reference[i].translation() - reference[i - 1].translation()).norm();
      const Eigen::Isometry3d de = estimate[i - 1].inverse() * estimate[i];
      const Eigen::Isometry3d dr = reference[i - 1].inverse() * reference[i];
      const Eigen::Isometry3d d = dr.inverse() * de;
      rel_t += d.translation().norm();
      rel_r += RotationAngleDeg(d.linear());
    }
  }
  c.mean_relative_translation_error_m = rel_t / (n - 1);
  c.mean_relative_rotation_error_deg = rel_r / (n - 1);
  c.drift_percent = c.reference_distance_m > 0 ? 100.0 * c.final_translation_error_m / c.reference_distance_m : 0;
  return c;
}

}  // namespace streetsim
