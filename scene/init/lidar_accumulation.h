// LiDAR accumulated in the world frame over the frames used, voxel-averaged as it goes.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "scene/init/dynamic_mask.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct FrameRange {
  int first = 0;
  int last = -1;  // exclusive; -1: to the end
  int stride = 1;
  // The log frame indices selected (clamped to the log).
  std::vector<int> Select(const DriveLog& log) const;
};
// "A:B" (frames A..B-1), "A:" (A to the end), ":B", "A:B:S" (every S-th); indices into
// DriveLog::frames.
absl::StatusOr<FrameRange> ParseFrameRange(const std::string& text);

struct AccumulationOptions {
  FrameRange frames;
  double voxel_m = 0.15;
  double min_range_m = 3.0;   // the ego car's roof and mounts
  double max_range_m = 60.0;
  // Drop points the dynamic mask flags, so moving vehicles do not smear along their path.
  bool drop_dynamic = false;
  DynamicMaskOptions dynamic;
};

struct AccumulatedCloud {
  std::vector<Eigen::Vector3f> points;  // world frame
  std::vector<float> reflectance;
  int frames_used = 0;
  size_t raw_points = 0;
  size_t dynamic_dropped = 0;
};

absl::StatusOr<AccumulatedCloud> AccumulateLidar(const DriveLog& log, const AccumulationOptions& options);

}  // namespace streetsim
