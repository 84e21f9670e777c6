// Opens any supported log directory, detecting its format:
//   KITTI raw drive     <drive>/{image_0N,velodyne_points,oxts}; also <date>/ with one drive, or
//                       <drive>/oxts itself (OXTS-only drives)
//   KITTI odometry      <seq>/calib.txt + image_0..3 / image_l / image_r
//   COLMAP              <root>/{sparse/0, sparse, sparse_*}/cameras.{txt,bin}, or the model dir
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"
#include "scene/log/kitti_raw_reader.h"

namespace streetsim {

struct OpenLogOptions {
  PoseSource pose_source = PoseSource::kAuto;  // KITTI raw only
};

// "kitti_raw", "kitti_odometry", "colmap", or NotFound/InvalidArgument explaining why not.
absl::StatusOr<std::string> DetectLogFormat(const std::string& path, std::string* resolved_dir);

absl::StatusOr<DriveLog> OpenLog(const std::string& path, const OpenLogOptions& options = {});

}  // namespace streetsim
