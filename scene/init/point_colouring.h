// Colours world points from the camera images they project into.
//
// Per camera frame, a coarse z-buffer (cells of cell_px pixels, nearest point per cell) decides
// visibility: a point farther than the nearest one in its cell by more than the tolerance is
// hidden in that view and takes no colour from it. A point's colour is the mean of the bilinear
// samples of the views that see it; points no view sees are reported as unseen.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct ColouringOptions {
  FrameRange frames;
  int cell_px = 4;
  double hidden_rel = 0.05;   // tolerance: hidden_abs_m + hidden_rel * depth
  double hidden_abs_m = 0.3;
  double min_depth_m = 0.5;
};

struct PointColours {
  std::vector<Eigen::Vector3f> rgb;  // linear 0..1 (8-bit values / 255)
  std::vector<int> views;            // how many views coloured each point; 0 = unseen
};

absl::StatusOr<PointColours> ColourPoints(const DriveLog& log, const std::vector<Eigen::Vector3f>& points_world,
                                          const ColouringOptions& options);

}  // namespace streetsim
