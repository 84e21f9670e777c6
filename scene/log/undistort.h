// Lens distortion for the COLMAP camera models. The renderer is pinhole-only, so images from
// distorted cameras are resampled onto the pinhole camera with the same K before use.
#pragma once

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

// Normalised undistorted image point (x/z, y/z) -> distorted normalised point.
Eigen::Vector2d DistortNormalized(const CameraIntrinsics& k, const Eigen::Vector2d& xy);

// Camera-frame point -> pixel (with distortion); false behind the camera.
bool ProjectToPixel(const CameraIntrinsics& k, const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv);

// The image as the pinhole camera with the same fx, fy, cx, cy would have seen it (bilinear; pixels
// that map outside the source are black). Pinhole input is returned as is.
absl::StatusOr<cv::Mat> UndistortImage(const cv::Mat& image, const CameraIntrinsics& k);

}  // namespace streetsim
