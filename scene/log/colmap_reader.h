// COLMAP sparse models, text (cameras.txt, images.txt, points3D.txt) and binary (*.bin).
//
// Camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; others are refused by
// name. COLMAP puts the image origin at the corner of the top-left pixel, OpenCV at its centre, so
// principal points are shifted by -0.5 px into CameraIntrinsics. Image poses are T_cam_from_world
// (qvec w, x, y, z + tvec); as a DriveLog the world is COLMAP's world and ego = camera (no GNSS, no
// times: frames in image-name order, 10 Hz assumed and reported).
#pragma once

#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

// DriveLog::pose_source of a log read from a COLMAP model: poses estimated from its own images
// (training leaves them unrefined: scene/train/config/run_resolution.h FitPosesToLog).
inline constexpr char kColmapPoseSource[] = "colmap";

struct ColmapCamera {
  uint32_t id = 0;
  std::string model;  // "PINHOLE", ...
  int width = 0, height = 0;
  std::vector<double> params;  // COLMAP order and convention
};

struct ColmapImage {
  uint32_t id = 0;
  Eigen::Quaterniond q_cam_from_world = Eigen::Quaterniond::Identity();
  Eigen::Vector3d t_cam_from_world = Eigen::Vector3d::Zero();
  uint32_t camera_id = 0;
  std::string name;
  Eigen::Isometry3d T_cam_from_world() const;
};

struct ColmapPoint {
  uint64_t id = 0;
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  Eigen::Matrix<uint8_t, 3, 1> rgb = Eigen::Matrix<uint8_t, 3, 1>::Zero();
  double error = 0;
};

struct ColmapModel {
  std::map<uint32_t, ColmapCamera> cameras;
  std::vector<ColmapImage> images;  // file order
  std::vector<ColmapPoint> points;
};

// Errors name the file and line (text) or byte offset (binary).
absl::StatusOr<ColmapModel> ReadColmapText(const std::string& model_dir);
absl::StatusOr<ColmapModel> ReadColmapBinary(const std::string& model_dir);
// Binary when cameras.bin exists, else text.
absl::StatusOr<ColmapModel> ReadColmapModel(const std::string& model_dir);
// Binary model (cameras.bin, images.bin without 2-D points, points3D.bin without tracks).
absl::Status WriteColmapBinary(const ColmapModel& model, const std::string& model_dir);

// COLMAP camera -> CameraIntrinsics (principal point shifted to the OpenCV convention).
absl::StatusOr<CameraIntrinsics> ColmapIntrinsics(const ColmapCamera& camera);

// A DriveLog from a model directory and the directory holding its images.
absl::StatusOr<DriveLog> ReadColmapLog(const std::string& model_dir, const std::string& images_dir);

// Finds the model and image directories of a COLMAP project root: a model in sparse/0, sparse,
// or sparse_*; images in images/ or, for a model dir named *_images_N, images_N.
absl::StatusOr<DriveLog> ReadColmapProject(const std::string& root);

}  // namespace streetsim
