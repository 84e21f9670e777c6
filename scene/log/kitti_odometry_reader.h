// KITTI odometry sequences: calib.txt (P0..P3 [+ Tr], labelled "P0: ..." or bare lines in that
// order), poses.txt (T_world_from_cam0, 3x4 per line, optional), times.txt (seconds, optional),
// image_0..image_3 or image_l/image_r (left/right grayscale), velodyne/ (.bin, optional, needs Tr).
//
// Frames: ego = forward-left-up at the rectified left camera 0 (T_ego_from_cam0 is the fixed
// axis swap, no translation); world = the ego frame at frame 0. Cameras are rectified pinholes.
// Frames without a pose (poses.txt shorter than the image list) are skipped and reported.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

absl::StatusOr<DriveLog> ReadKittiOdometry(const std::string& sequence_dir);

// The rotation taking OpenCV camera axes (x right, y down, z forward) to forward-left-up.
Eigen::Isometry3d EgoFromOpenCvCamera();

}  // namespace streetsim
