// KITTI OXTS (GNSS/IMU) records -> ego poses in a local ENU world.
//
// Each record is one text line of 30 values (oxts/dataformat.txt). The pose follows KITTI's devkit
// (R = Rz(yaw) Ry(pitch) Rx(roll), ego = the OXTS unit, x forward, y left, z up) except that the
// translation comes from GeographicLib::LocalCartesian at the first valid record (ENU) instead of
// the devkit's Mercator projection, and the world is that ENU frame (not the first pose).
//
// Records with a non-finite position or orientation are reported and bridged, never returned as
// NaN poses: positions are dead-reckoned from the recorded ENU velocities forwards from the last
// good record and backwards from the next, blended linearly in time so that both ends join (the
// velocity integration error is spread over the gap instead of showing as a jump); a gap without
// usable velocities is interpolated linearly. Orientations are slerped across a gap.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"

namespace streetsim {

inline constexpr int kOxtsValues = 30;

struct OxtsRecord {
  std::array<double, kOxtsValues> v{};
  double lat() const { return v[0]; }
  double lon() const { return v[1]; }
  double alt() const { return v[2]; }
  double roll() const { return v[3]; }
  double pitch() const { return v[4]; }
  double yaw() const { return v[5]; }
  double vn() const { return v[6]; }
  double ve() const { return v[7]; }
  double vf() const { return v[8]; }
  double vl() const { return v[9]; }
  double vu() const { return v[10]; }
  bool PositionValid() const;
  bool OrientationValid() const;
  bool VelocityValid() const;
};

// One line of an oxts data file. Wrong value counts and non-numbers are errors naming the file and
// line; NaN values are accepted (bridged later).
absl::StatusOr<OxtsRecord> ParseOxtsRecord(const std::string& line, const std::string& path,
                                           int line_number);

struct OxtsTrack {
  std::vector<int> source_index;  // data file number per record kept
  std::vector<int64_t> time_us;   // absolute UNIX us, or index * 100'000 without timestamps.txt
  bool time_is_absolute = false;
  std::vector<OxtsRecord> records;
  std::vector<Eigen::Isometry3d> T_world_from_ego;  // all finite
  GeoOrigin origin;
  std::vector<int> bridged;  // record indices whose pose was bridged
  std::vector<std::string> problems;
};

// Reads oxts/ (data/NNNNNNNNNN.txt + timestamps.txt). Missing timestamps: 10 Hz assumed and
// reported. More files than timestamps (or the reverse): the unmatched tail is skipped and
// reported. No valid position at all: error.
absl::StatusOr<OxtsTrack> ReadOxtsDirectory(const std::string& oxts_dir);

// Poses from records (exposed for tests): ENU at the first valid record, bridging as above.
absl::StatusOr<OxtsTrack> OxtsTrackFromRecords(std::vector<OxtsRecord> records,
                                               std::vector<int64_t> time_us,
                                               std::vector<int> source_index);

// KITTI timestamps.txt -> absolute UNIX microseconds, one per non-empty line.
absl::StatusOr<std::vector<int64_t>> ReadKittiTimestamps(const std::string& path);

}  // namespace streetsim
