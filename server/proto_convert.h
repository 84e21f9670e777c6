// Validated conversions between wire messages and internal types.
#pragma once

#include <string>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "render/camera.h"
#include "streetsim/v1/common.pb.h"

namespace streetsim::server {

// INVALID_ARGUMENT for a missing rotation, non-finite values, or |q| not within 1e-3 of 1.
// `field` names the field in the message.
absl::StatusOr<Eigen::Isometry3d> PoseFromProto(const v1::Pose& pose, const std::string& field);
void PoseToProto(const Eigen::Isometry3d& T, v1::Pose* out);

struct Intrinsics {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
};
// Positive size (limits checked by the caller), positive finite focal lengths, finite centre.
absl::StatusOr<Intrinsics> IntrinsicsFromProto(const v1::PinholeIntrinsics& k, const std::string& field);
void IntrinsicsToProto(const Intrinsics& k, v1::PinholeIntrinsics* out);

// Linear interpolation of translation, slerp of rotation; `t` in [0, 1].
Eigen::Isometry3d InterpolatePose(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b, double t);

}  // namespace streetsim::server
