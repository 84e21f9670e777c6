// A spinning LiDAR: beam elevation table, azimuth columns, range limits, mounting, sweep timing.
//
// Sensor frame: x forward, y left, z up (Velodyne / KITTI). A return at sensor-frame point p has
// azimuth atan2(p.y, p.x) and elevation atan2(p.z, |p.xy|).
//
// Range image layout (beams x columns, docs/lidar.md):
//   - row b is beam b of the table, beam 0 the highest; rows are not uniformly spaced in elevation,
//     so elevations map to a continuous beam coordinate by piecewise-linear interpolation of the
//     table (beam b's centre is coordinate b; linear extrapolation past the first/last beam).
//   - column c is centred on azimuth pi - (c + 0.5) 2 pi / columns: column 0 starts behind the
//     sensor (azimuth +pi, its left-rear) and the columns turn clockwise seen from above (left to
//     right, as in a camera image), so straight ahead (azimuth 0) is between columns
//     columns/2 - 1 and columns/2. Continuous column coordinate u = (pi - az) columns / 2 pi - 0.5.
//   - the sweep also runs in column order: column c is measured at
//     sweep_start_us + (c + 0.5) sweep_duration_us / columns (rolling sweep).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/status.h"

namespace streetsim {

struct LidarModel {
  std::string name = "kitti_hdl64e";
  // Degrees, strictly decreasing (beam 0 is the highest).
  std::vector<double> beam_elevation_deg;
  int columns = 2048;
  double min_range_m = 2.5;   // returns nearer than this are dropped (the ego car's roof)
  double max_range_m = 120.0;
  Eigen::Isometry3d T_ego_from_lidar = Eigen::Isometry3d::Identity();
  int64_t sweep_duration_us = 100'000;  // 10 Hz

  int beams() const { return static_cast<int>(beam_elevation_deg.size()); }

  // At least 2 beams (strictly decreasing, within (-90, 90) degrees), 1..65536 columns,
  // 0 <= min < max finite ranges, a finite rigid mounting, sweep duration >= 0.
  absl::Status Validate() const;

  // Continuous beam coordinate of an elevation (radians) and its derivative d(beam)/d(elevation).
  double BeamCoordinate(double elevation_rad, double* d_beam_d_elevation = nullptr) const;
  // Elevation (radians) of beam b's centre.
  double BeamElevationRad(int b) const;
  // Continuous column coordinate of an azimuth (radians, any value; wrapped into [-0.5, columns - 0.5)).
  double ColumnCoordinate(double azimuth_rad) const;
  // Azimuth (radians) of column c's centre.
  double ColumnAzimuthRad(int c) const;
  // Unit ray direction (sensor frame) of the centre of range-image pixel (beam, column).
  Eigen::Vector3d RayDirection(int beam, int column) const;
  // Microseconds after the sweep start at which column c is measured.
  int64_t ColumnTimeOffsetUs(int column) const;
};

// KITTI's Velodyne HDL-64E: 64 beams (table estimated from the shared KITTI raw scans, see
// lidar_model.cc), 10 Hz, mounted per KITTI's calibration (T_ego_from_lidar left identity: the
// DriveLog's LidarSensor holds the log's own mounting; copy it in).
LidarModel KittiHdl64e(int columns = 2048);

}  // namespace streetsim
