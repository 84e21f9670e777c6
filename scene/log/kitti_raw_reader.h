// KITTI raw drives: <date>/<date>_drive_NNNN_sync/{image_0[0-3],velodyne_points,oxts} with the
// day's calib_{cam_to_cam,velo_to_cam,imu_to_velo}.txt beside the drive (or inside it).
//
// Frames: ego = the OXTS/IMU unit (x forward, y left, z up). Cameras are the rectified ones:
// T_camN_from_velo = [I | K^-1 p4(P_rect_0N)] * R_rect_00 * T_cam0_from_velo, and
// T_ego_from_velo = inverse(T_velo_from_imu). Images are rectified: pinhole, no distortion.
//
// Poses (first available unless forced): oxts/ (world = ENU at the first valid record; see
// oxts.h), poses_velo_icp_estimated.txt or poses.txt in the drive (T_world_from_velo per frame;
// world = the ego frame at frame 0), else LiDAR odometry (lidar_odometry.h).
//
// Time: each sensor's timestamps.txt (absolute UNIX us); the frame time is oxts', else the first
// camera's, else the LiDAR's. Without any: 10 Hz from 0, reported.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

enum class PoseSource { kAuto, kOxts, kPosesFile, kLidarOdometry };

struct KittiRawOptions {
  PoseSource pose_source = PoseSource::kAuto;
};

absl::StatusOr<DriveLog> ReadKittiRaw(const std::string& drive_dir, const KittiRawOptions& options = {});

// The three calibration files -> sensors (exposed for tests of bad calibration).
struct KittiRawCalibration {
  Eigen::Isometry3d T_ego_from_velo = Eigen::Isometry3d::Identity();
  // Index = camera number 0..3.
  Eigen::Isometry3d T_cam_from_velo[4];
  CameraIntrinsics intrinsics[4];
};
absl::StatusOr<KittiRawCalibration> ReadKittiRawCalibration(const std::string& calib_dir);

}  // namespace streetsim
