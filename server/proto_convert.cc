#include "server/proto_convert.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace streetsim::server {

absl::StatusOr<Eigen::Isometry3d> PoseFromProto(const v1::Pose& pose, const std::string& field) {
  if (!pose.has_rotation()) {
    return absl::InvalidArgumentError(absl::StrCat(field, ".rotation is missing"));
  }
  const v1::Vec3& t = pose.translation_m();
  const v1::Quaternion& q = pose.rotation();
  for (double v : {t.x(), t.y(), t.z()}) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".translation_m is not finite"));
    }
  }
  for (double v : {q.w(), q.x(), q.y(), q.z()}) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(field, ".rotation is not finite"));
    }
  }
  const double norm = std::sqrt(q.w() * q.w() + q.x() * q.x() + q.y() * q.y() + q.z() * q.z());
  if (std::abs(norm - 1.0) > 1e-3) {
    return absl::InvalidArgumentError(absl::StrCat(field, ".rotation is not a unit quaternion (|q| = ",
                                                   norm, ")"));
  }
  Eigen::Quaterniond rot(q.w() / norm, q.x() / norm, q.y() / norm, q.z() / norm);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = rot.toRotationMatrix();
  T.translation() = Eigen::Vector3d(t.x(), t.y(), t.z());
  return T;
}

void PoseToProto(const Eigen::Isometry3d& T, v1::Pose* out) {
  Eigen::Quaterniond q(T.rotation());
  q.normalize();
  if (q.w() < 0) q.coeffs() *= -1;
  out->mutable_translation_m()->set_x(T.translation().x());
  out->mutable_translation_m()->set_y(T.translation().y());
  out->mutable_translation_m()->set_z(T.translation().z());
  out->mutable_rotation()->set_w(q.w());
  out->mutable_rotation()->set_x(q.x());
  out->mutable_rotation()->set_y(q.y());
  out->mutable_rotation()->set_z(q.z());
}

absl::StatusOr<Intrinsics> IntrinsicsFromProto(const v1::PinholeIntrinsics& k, const std::string& field) {
  if (k.width() <= 0 || k.height() <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": width and height must be positive"));
  }
  if (!std::isfinite(k.fx()) || !std::isfinite(k.fy()) || k.fx() <= 0 || k.fy() <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": fx and fy must be positive and finite"));
  }
  if (!std::isfinite(k.cx()) || !std::isfinite(k.cy())) {
    return absl::InvalidArgumentError(absl::StrCat(field, ": cx and cy must be finite"));
  }
  return Intrinsics{k.width(), k.height(), k.fx(), k.fy(), k.cx(), k.cy()};
}

void IntrinsicsToProto(const Intrinsics& k, v1::PinholeIntrinsics* out) {
  out->set_width(k.width);
  out->set_height(k.height);
  out->set_fx(k.fx);
  out->set_fy(k.fy);
  out->set_cx(k.cx);
  out->set_cy(k.cy);
}

Eigen::Isometry3d InterpolatePose(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b, double t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  const Eigen::Quaterniond qa(a.rotation()), qb(b.rotation());
  T.linear() = qa.slerp(t, qb).toRotationMatrix();
  T.translation() = (1 - t) * a.translation() + t * b.translation();
  return T;
}

}  // namespace streetsim::server
