// Dynamic-point mask: LiDAR points of one scan that a neighbouring scan, placed with the ego
// poses (ego-motion compensation), contradicts. A neighbour contradicts a point when both
//   - it saw through the point's place: its return in that direction (smallest range in the
//     direction's bin of its range image) lies beyond the point, so the place was empty then; and
//   - none of its points lies near the point (a static surface is seen again where it was).
// Free space, not mere absence, is the evidence: a surface occluded in the neighbour (its return
// is nearer) or outside its view (no return) is never flagged. The nearness test keeps grazing
// ground, where range-image bins are coarse, from being flagged. Used later for PSNR*.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct DynamicMaskOptions {
  int frame_gap = 5;           // neighbours at frame +- gap (0.5 s at 10 Hz: a car at 5 m/s moves 2.5 m)
  double min_range_m = 3.0;    // the ego car's own returns are not judged
  double max_range_m = 40.0;   // farther, scans are too sparse to confirm each other
  double threshold_m = 0.3;    // distance to the nearest neighbour-scan point...
  double threshold_per_m = 0.015;  // ...plus this per metre of range (beam spacing grows)
  double azimuth_bin_deg = 0.4;    // range-image bins for the free-space test
  double elevation_bin_deg = 0.5;
};

struct DynamicMask {
  // One per point of the frame's scan as loaded (LoadLidarScan order): 1 = dynamic.
  std::vector<uint8_t> dynamic;
  std::vector<uint8_t> judged;  // 0: outside the judged range (never flagged)
  size_t num_dynamic = 0;
};

// Mask for log.frames[frame]'s first LiDAR scan.
absl::StatusOr<DynamicMask> ComputeDynamicMask(const DriveLog& log, int frame,
                                               const DynamicMaskOptions& options = {});
// The same for the frame's scan already loaded (LoadLidarScan's points, sensor frame); only the
// neighbours are read.
absl::StatusOr<DynamicMask> ComputeDynamicMask(const DriveLog& log, int frame, const std::vector<Eigen::Vector3f>& scan,
                                               const DynamicMaskOptions& options = {});

struct NeighbourScan {
  std::vector<Eigen::Vector3f> points;  // in the neighbour's own sensor frame
  Eigen::Isometry3d T_scan_from_neighbour = Eigen::Isometry3d::Identity();
};

// The core on in-memory scans (exposed for tests); `scan` in its sensor frame.
DynamicMask DynamicMaskFromScans(const std::vector<Eigen::Vector3f>& scan,
                                 const std::vector<NeighbourScan>& neighbours,
                                 const DynamicMaskOptions& options);

}  // namespace streetsim
