#include "render/camera.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace streetsim {

absl::Status PinholeCamera::Validate() const {
  if (width < 1 || height < 1 || width > kMaxImageSide || height > kMaxImageSide) {
    return absl::InvalidArgumentError(absl::StrCat("camera size ", width, "x", height,
                                                   " outside 1..", kMaxImageSide));
  }
  for (double f : {fx, fy}) {
    if (!std::isfinite(f) || f <= 0) {
      return absl::InvalidArgumentError(absl::StrCat("focal length ", f, " must be finite and > 0"));
    }
  }
  if (!std::isfinite(cx) || !std::isfinite(cy)) {
    return absl::InvalidArgumentError("principal point is not finite");
  }
  const Eigen::Matrix4d m = T_world_from_cam.matrix();
  if (!m.allFinite()) return absl::InvalidArgumentError("T_world_from_cam is not finite");
  const Eigen::Matrix3d r = m.topLeftCorner<3, 3>();
  if ((r * r.transpose() - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff() > 1e-6 ||
      std::abs(r.determinant() - 1.0) > 1e-6) {
    return absl::InvalidArgumentError("T_world_from_cam rotation is not orthonormal (det +1)");
  }
  if (m(3, 0) != 0 || m(3, 1) != 0 || m(3, 2) != 0 || m(3, 3) != 1) {
    return absl::InvalidArgumentError("T_world_from_cam bottom row must be 0 0 0 1");
  }
  return absl::OkStatus();
}

}  // namespace streetsim
