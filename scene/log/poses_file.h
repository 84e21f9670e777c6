// KITTI-style pose files: one row-major 3x4 [R | t] per line (T_world_from_x), '#' comments.
// Used by KITTI odometry poses.txt, the raw clip's poses_velo_icp_estimated.txt and
// `streetsim log poses --out`.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"

namespace streetsim {

// Errors name the file and line: wrong value count, non-numbers, non-finite values, a rotation
// block that is not a rotation (tolerance 1e-3; it is re-orthonormalised).
absl::StatusOr<std::vector<Eigen::Isometry3d>> ReadPosesFile(const std::string& path);

// Writes atomically; `comment` (may be empty) becomes a leading '# ' line.
absl::Status WritePosesFile(const std::string& path, const std::vector<Eigen::Isometry3d>& poses,
                            const std::string& comment);

}  // namespace streetsim
