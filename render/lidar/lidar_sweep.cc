#include "render/lidar/lidar_sweep.h"

namespace streetsim {
namespace {

bool IsRigid(const Eigen::Isometry3d& T) {
  const Eigen::Matrix3d R = T.linear();
  return T.matrix().allFinite() && (R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) &&
         R.determinant() > 0 && T.matrix().row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1), 0);
}

}  // namespace

absl::Status ValidateSweepPose(const LidarSweepPose& sweep) {
  if (!IsRigid(sweep.T_world_from_lidar_start)) {
    return absl::InvalidArgumentError("T_world_from_lidar (sweep start) must be a finite rigid transform");
  }
  if (!IsRigid(sweep.T_world_from_lidar_end)) {
    return absl::InvalidArgumentError("T_world_from_lidar_end must be a finite rigid transform");
  }
  return absl::OkStatus();
}

Eigen::Isometry3d ColumnPose(const LidarSweepPose& sweep, int columns, int c) {
  if (sweep.is_static()) return sweep.T_world_from_lidar_start;
  const double s = (c + 0.5) / columns;
  // The rotations are re-orthonormalised through the quaternion (a validated pose is rigid to 1e-6).
  const Eigen::Quaterniond q0(sweep.T_world_from_lidar_start.linear());
  const Eigen::Quaterniond q1(sweep.T_world_from_lidar_end.linear());
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = q0.normalized().slerp(s, q1.normalized()).toRotationMatrix();
  T.translation() = (1 - s) * sweep.T_world_from_lidar_start.translation() +
                    s * sweep.T_world_from_lidar_end.translation();
  return T;
}

void ColumnPoseTable(const LidarSweepPose& sweep, int columns, std::vector<double>* table) {
  table->resize(static_cast<size_t>(columns) * 12);
  const bool fixed = sweep.is_static();
  const Eigen::Isometry3d T_fixed = sweep.T_world_from_lidar_start.inverse();
  for (int c = 0; c < columns; ++c) {
    const Eigen::Isometry3d T_lw = fixed ? T_fixed : ColumnPose(sweep, columns, c).inverse();
    double* e = table->data() + static_cast<size_t>(c) * 12;
    for (int r = 0; r < 3; ++r) {
      for (int k = 0; k < 3; ++k) e[r * 3 + k] = T_lw.linear()(r, k);
      e[9 + r] = T_lw.translation()[r];
    }
  }
}

}  // namespace streetsim
