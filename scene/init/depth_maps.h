// Sparse depth maps per camera frame from the frame's LiDAR scan, for the depth loss: each point
// is moved into the camera (T_cam_from_lidar = inverse(T_ego_from_cam) * T_ego_from_lidar, same
// ego pose: camera and LiDAR of a KITTI frame are synchronised) and z-buffered, nearest wins.
#pragma once

#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

// CV_32FC1, camera z in metres, 0 = no return. Points closer than min_depth_m are ignored.
cv::Mat ProjectDepth(const std::vector<Eigen::Vector3f>& points_lidar, const Eigen::Isometry3d& T_cam_from_lidar,
                     const CameraIntrinsics& intrinsics, double min_depth_m = 0.5);

// Depth map for camera observation `camera_obs` of log.frames[frame] from that frame's first scan.
absl::StatusOr<cv::Mat> SparseDepthMap(const DriveLog& log, int frame, int camera_obs);

}  // namespace streetsim
