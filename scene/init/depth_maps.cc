#include "scene/init/depth_maps.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "scene/log/undistort.h"

namespace streetsim {

cv::Mat ProjectDepth(const std::vector<Eigen::Vector3f>& points_lidar, const Eigen::Isometry3d& T_cam_from_lidar,
                     const CameraIntrinsics& k, double min_depth_m) {
  cv::Mat depth(k.height, k.width, CV_32FC1, cv::Scalar(0));
  for (const Eigen::Vector3f& p : points_lidar) {
    const Eigen::Vector3d c = T_cam_from_lidar * p.cast<double>();
    if (c.z() < min_depth_m) continue;
    Eigen::Vector2d uv;
    if (!ProjectToPixel(k, c, &uv)) continue;
    const long u = std::lround(uv.x()), v = std::lround(uv.y());
    if (u < 0 || v < 0 || u >= k.width || v >= k.height) continue;
    float& d = depth.at<float>(static_cast<int>(v), static_cast<int>(u));
    const float z = static_cast<float>(c.z());
    if (d == 0 || z < d) d = z;  // nearest wins: the farther point is hidden behind it
  }
  return depth;
}

absl::StatusOr<cv::Mat> SparseDepthMap(const DriveLog& log, int frame, int camera_obs) {
  if (frame < 0 || frame >= static_cast<int>(log.frames.size())) {
    return absl::OutOfRangeError(absl::StrCat("frame ", frame, " out of range"));
  }
  const Frame& f = log.frames[frame];
  if (camera_obs < 0 || camera_obs >= static_cast<int>(f.cameras.size())) {
    return absl::OutOfRangeError(absl::StrCat("frame ", frame, " has no camera observation ", camera_obs));
  }
  if (f.lidars.empty()) return absl::FailedPreconditionError(absl::StrCat("frame ", frame, " has no LiDAR scan"));
  absl::StatusOr<LidarScan> scan = LoadLidarScan(f.lidars[0].path);
  if (!scan.ok()) return scan.status();
  const CameraSensor& cam = log.cameras[f.cameras[camera_obs].camera];
  const Eigen::Isometry3d T_cam_from_lidar = cam.T_ego_from_cam.inverse() * log.lidars[f.lidars[0].lidar].T_ego_from_lidar;
  return ProjectDepth(scan->points, T_cam_from_lidar, cam.intrinsics);
}

}  // namespace streetsim
