#include "scene/init/dynamic_mask.h"

#include <algorithm>
#include <cmath>
#include <memory>

#include "absl/strings/str_cat.h"
#include "scene/log/kdtree.h"
#include "scene/log/voxel_hash.h"

namespace streetsim {

namespace {

// Smallest range per (azimuth, elevation) bin: what the sensor saw in each direction.
class RangeImage {
 public:
  RangeImage(const std::vector<Eigen::Vector3f>& points, const DynamicMaskOptions& o)
      : az_bins_(static_cast<int>(std::ceil(360.0 / o.azimuth_bin_deg))),
        el_bins_(static_cast<int>(std::ceil(180.0 / o.elevation_bin_deg))),
        az_scale_(1.0 / (o.azimuth_bin_deg * M_PI / 180)),
        el_scale_(1.0 / (o.elevation_bin_deg * M_PI / 180)),
        min_range_(static_cast<size_t>(az_bins_) * el_bins_, 0.0f) {
    for (const Eigen::Vector3f& p : points) {
      const float r = p.norm();
      if (r < 1.0f) continue;
      float& m = min_range_[Bin(p, r)];
      if (m == 0 || r < m) m = r;
    }
  }
  // 0: no return in that direction.
  float MinRange(const Eigen::Vector3f& p, float r) const { return min_range_[Bin(p, r)]; }

 private:
  size_t Bin(const Eigen::Vector3f& p, float r) const {
    const double az = std::atan2(p.y(), p.x()) + M_PI;             // 0..2pi
    const double el = std::asin(std::clamp(p.z() / r, -1.0f, 1.0f)) + M_PI / 2;  // 0..pi
    const int a = std::min(az_bins_ - 1, static_cast<int>(az * az_scale_));
    const int e = std::min(el_bins_ - 1, static_cast<int>(el * el_scale_));
    return static_cast<size_t>(e) * az_bins_ + a;
  }
  int az_bins_, el_bins_;
  double az_scale_, el_scale_;
  std::vector<float> min_range_;
};

}  // namespace

DynamicMask DynamicMaskFromScans(const std::vector<Eigen::Vector3f>& scan,
                                 const std::vector<NeighbourScan>& neighbours,
                                 const DynamicMaskOptions& options) {
  DynamicMask mask;
  mask.dynamic.assign(scan.size(), 0);
  mask.judged.assign(scan.size(), 0);
  struct Prepared {
    std::vector<Eigen::Vector3f> in_scan_frame;  // thinned to 5 cm voxels: smaller trees, same surfaces
    KdTree3 tree;
    std::unique_ptr<RangeImage> range;
    Eigen::Isometry3f T_neighbour_from_scan;
  };
  std::vector<Prepared> prepared(neighbours.size());
  for (size_t n = 0; n < neighbours.size(); ++n) {
    const Eigen::Isometry3f T = neighbours[n].T_scan_from_neighbour.cast<float>();
    std::vector<Eigen::Vector3f> moved;
    moved.reserve(neighbours[n].points.size());
    for (const Eigen::Vector3f& p : neighbours[n].points) moved.push_back(T * p);
    prepared[n].in_scan_frame = VoxelDownsample(moved, 0.05);
    prepared[n].tree.Build(&prepared[n].in_scan_frame);
    prepared[n].range = std::make_unique<RangeImage>(neighbours[n].points, options);
    prepared[n].T_neighbour_from_scan = neighbours[n].T_scan_from_neighbour.inverse().cast<float>();
  }
  const float lo = static_cast<float>(options.min_range_m * options.min_range_m);
  const float hi = static_cast<float>(options.max_range_m * options.max_range_m);
  for (size_t i = 0; i < scan.size(); ++i) {
    const float r2 = scan[i].squaredNorm();
    if (r2 < lo || r2 > hi) continue;
    mask.judged[i] = 1;
    const float tau = static_cast<float>(options.threshold_m + options.threshold_per_m * std::sqrt(r2));
    for (const Prepared& nb : prepared) {
      const Eigen::Vector3f q = nb.T_neighbour_from_scan * scan[i];
      const float rq = q.norm();
      const float seen = nb.range->MinRange(q, rq);
      if (seen == 0 || seen < rq + tau) continue;  // no return, or the place was hidden / occupied
      if (nb.tree.Nearest(scan[i], tau * tau) >= 0) continue;  // seen again where it was
      mask.dynamic[i] = 1;
      ++mask.num_dynamic;
      break;
    }
  }
  return mask;
}

namespace {
// The frame's first LiDAR's scan, or null.
const LidarObservation* ScanOf(const DriveLog& log, int frame) {
  for (const LidarObservation& o : log.frames[frame].lidars) {
    if (o.lidar == 0) return &o;
  }
  return nullptr;
}
}  // namespace

absl::StatusOr<DynamicMask> ComputeDynamicMask(const DriveLog& log, int frame,
                                               const DynamicMaskOptions& options) {
  if (frame < 0 || frame >= static_cast<int>(log.frames.size())) {
    return absl::OutOfRangeError(absl::StrCat("frame ", frame, " not in 0..", log.frames.size() - 1));
  }
  const LidarObservation* obs = ScanOf(log, frame);
  if (obs == nullptr) return absl::FailedPreconditionError(absl::StrCat("frame ", frame, " has no LiDAR scan"));
  absl::StatusOr<LidarScan> scan = LoadLidarScan(obs->path);
  if (!scan.ok()) return scan.status();
  return ComputeDynamicMask(log, frame, scan->points, options);
}

absl::StatusOr<DynamicMask> ComputeDynamicMask(const DriveLog& log, int frame, const std::vector<Eigen::Vector3f>& scan,
                                               const DynamicMaskOptions& options) {
  if (frame < 0 || frame >= static_cast<int>(log.frames.size())) {
    return absl::OutOfRangeError(absl::StrCat("frame ", frame, " not in 0..", log.frames.size() - 1));
  }
  const Eigen::Isometry3d T_ego_from_lidar = log.lidars[0].T_ego_from_lidar;
  const Eigen::Isometry3d T_lidar_from_world =
      (log.frames[frame].T_world_from_ego * T_ego_from_lidar).inverse();
  std::vector<NeighbourScan> neighbours;
  for (int f : {frame - options.frame_gap, frame + options.frame_gap}) {
    if (f < 0 || f >= static_cast<int>(log.frames.size())) continue;
    const LidarObservation* n = ScanOf(log, f);
    if (n == nullptr) continue;
    absl::StatusOr<LidarScan> other = LoadLidarScan(n->path);
    if (!other.ok()) return other.status();
    neighbours.push_back({std::move(other->points),
                          T_lidar_from_world * log.frames[f].T_world_from_ego * T_ego_from_lidar});
  }
  if (neighbours.empty()) {
    return absl::FailedPreconditionError(absl::StrCat("frame ", frame, ": no neighbouring scan within ",
                                                      options.frame_gap, " frames"));
  }
  return DynamicMaskFromScans(scan, neighbours, options);
}

}  // namespace streetsim
