// DriveLog: one driving log on disk, read into memory as sensors, frames and poses.
//
// Heavy data (images, LiDAR scans) stays on disk: observations name their files and are loaded on
// demand (LoadImageRgb, LoadLidarScan), so a long log costs only its metadata in RAM.
//
// Conventions (../shared/docs/architecture.md):
//   - time_us: int64 microseconds. Absolute UNIX time when the log has timestamps
//     (time_is_absolute), else frame_index * 100'000 from 0 (10 Hz assumed, listed in problems).
//   - T_a_from_b maps points in frame b to frame a.
//   - world: local ENU at the first valid GNSS record when the log has GNSS (has_gnss); else the
//     log's own world (COLMAP) or the ego frame of the first frame (KITTI raw without oxts,
//     KITTI odometry).
//   - ego: forward-left-up (KITTI: the IMU/GNSS unit). Camera-only COLMAP logs: ego = camera.
//   - cameras: OpenCV (x right, y down, z forward).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace streetsim {

// The frame period a log without timestamps is given (10 Hz, KITTI's and most logs' rate).
inline constexpr int64_t kAssumedFrameUs = 100'000;

enum class DistortionModel {
  kNone,          // pinhole (rectified images)
  kSimpleRadial,  // COLMAP SIMPLE_RADIAL: k1
  kRadial,        // COLMAP RADIAL: k1, k2
  kOpenCv,        // COLMAP OPENCV: k1, k2, p1, p2
};
const char* DistortionModelName(DistortionModel model);

struct CameraIntrinsics {
  int width = 0;
  int height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;  // pixels, OpenCV convention (pixel centres at integers)
  DistortionModel model = DistortionModel::kNone;
  // Model parameters in the order of the model above; empty for kNone.
  std::vector<double> distortion;

  // OpenCV's (k1, k2, p1, p2) distortion vector for this model (zeros where absent).
  std::vector<double> OpenCvCoefficients() const;
  bool IsPinhole() const { return model == DistortionModel::kNone; }
};

struct CameraSensor {
  std::string name;  // e.g. "image_02", "colmap_cam_1"
  CameraIntrinsics intrinsics;
  Eigen::Isometry3d T_ego_from_cam = Eigen::Isometry3d::Identity();
  bool colour = true;  // false: the files are grayscale (loaded as RGB with equal channels)
};

struct LidarSensor {
  std::string name;  // e.g. "velodyne_points"
  Eigen::Isometry3d T_ego_from_lidar = Eigen::Isometry3d::Identity();
};

struct CameraObservation {
  int camera = 0;  // index into DriveLog::cameras
  int64_t time_us = 0;
  std::string path;
};

struct LidarObservation {
  int lidar = 0;  // index into DriveLog::lidars
  int64_t time_us = 0;
  std::string path;
};

struct Frame {
  int source_index = 0;  // frame number in the log's own files (e.g. 0000000012.png -> 12)
  int64_t time_us = 0;
  Eigen::Isometry3d T_world_from_ego = Eigen::Isometry3d::Identity();
  std::vector<CameraObservation> cameras;
  std::vector<LidarObservation> lidars;
};

// GNSS origin of the world frame (WGS84), present when the log has GNSS.
struct GeoOrigin {
  double latitude_deg = 0, longitude_deg = 0, altitude_m = 0;
};

struct DriveLog {
  std::string format;       // "kitti_raw", "kitti_oxts", "kitti_odometry", "colmap"
  std::string root;         // the directory read
  std::string pose_source;  // "oxts", "poses_velo_icp_estimated.txt", "lidar_odometry", ...
  bool time_is_absolute = false;
  bool has_gnss = false;
  std::optional<GeoOrigin> geo_origin;

  std::vector<CameraSensor> cameras;
  std::vector<LidarSensor> lidars;
  std::vector<Frame> frames;  // in time order, every pose finite

  // Sparse structure from the log itself (COLMAP points3D), world frame, RGB 0..255.
  std::vector<Eigen::Vector3d> sparse_points;
  std::vector<Eigen::Matrix<uint8_t, 3, 1>> sparse_colours;

  // Human-readable warnings: assumed values, skipped frames, bridged records.
  std::vector<std::string> problems;

  int64_t duration_us() const;
  // Sum of the ego translations between consecutive frames (metres).
  double distance_m() const;
};

// A LiDAR scan in its sensor frame.
struct LidarScan {
  std::vector<Eigen::Vector3f> points;
  std::vector<float> reflectance;  // one per point, 0..1 for KITTI
};

// Loads an observation's image as 8-bit RGB (CV_8UC3, channel order R, G, B); grayscale files
// become three equal channels. Errors name the file.
absl::StatusOr<cv::Mat> LoadImageRgb(const std::string& path);

// Reads a KITTI Velodyne .bin (float32 x, y, z, reflectance). Points with a non-finite
// coordinate are dropped (counted in *dropped when given); a file whose size is not a multiple of
// 16 bytes is an error naming the file.
absl::StatusOr<LidarScan> LoadLidarScan(const std::string& path, size_t* dropped = nullptr);

// PinholeCamera-style world pose of a camera observation.
inline Eigen::Isometry3d WorldFromCamera(const DriveLog& log, const Frame& frame,
                                         const CameraObservation& obs) {
  return frame.T_world_from_ego * log.cameras[obs.camera].T_ego_from_cam;
}

}  // namespace streetsim
