#include "scene/log/oxts.h"

#include <cmath>
#include <filesystem>

#include <GeographicLib/LocalCartesian.hpp>

#include "absl/strings/str_cat.h"
#include "scene/log/text_util.h"

namespace streetsim {
namespace {

Eigen::Matrix3d OxtsRotation(const OxtsRecord& r) {
  return (Eigen::AngleAxisd(r.yaw(), Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(r.pitch(), Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(r.roll(), Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

Eigen::Vector3d EnuVelocity(const OxtsRecord& r) { return Eigen::Vector3d(r.ve(), r.vn(), r.vu()); }

std::string IndexList(const std::vector<int>& indices, const std::vector<int>& source) {
  // Compact "20-40, 70-90" ranges of source indices.
  std::string out;
  for (size_t i = 0; i < indices.size();) {
    size_t j = i;
    while (j + 1 < indices.size() && source[indices[j + 1]] == source[indices[j]] + 1) ++j;
    if (!out.empty()) out += ", ";
    out += j == i ? absl::StrCat(source[indices[i]])
                  : absl::StrCat(source[indices[i]], "-", source[indices[j]]);
    i = j + 1;
  }
  return out;
}

}  // namespace

bool OxtsRecord::PositionValid() const {
  return std::isfinite(lat()) && std::isfinite(lon()) && std::isfinite(alt()) &&
         std::abs(lat()) <= 90 && std::abs(lon()) <= 180;
}
bool OxtsRecord::OrientationValid() const {
  return std::isfinite(roll()) && std::isfinite(pitch()) && std::isfinite(yaw());
}
bool OxtsRecord::VelocityValid() const {
  return std::isfinite(vn()) && std::isfinite(ve()) && std::isfinite(vu());
}

absl::StatusOr<OxtsRecord> ParseOxtsRecord(const std::string& line, const std::string& path,
                                           int line_number) {
  absl::StatusOr<std::vector<double>> values = ParseNumbers(line, path, line_number, kOxtsValues);
  if (!values.ok()) return values.status();
  OxtsRecord r;
  std::copy(values->begin(), values->end(), r.v.begin());
  return r;
}

absl::StatusOr<std::vector<int64_t>> ReadKittiTimestamps(const std::string& path) {
  absl::StatusOr<std::vector<std::string>> lines = ReadLines(path);
  if (!lines.ok()) return lines.status();
  std::vector<int64_t> times;
  for (size_t i = 0; i < lines->size(); ++i) {
    if (IsBlankOrComment((*lines)[i])) continue;
    absl::StatusOr<int64_t> t = ParseKittiTimestamp((*lines)[i], path, static_cast<int>(i + 1));
    if (!t.ok()) return t.status();
    if (!times.empty() && *t <= times.back()) {
      return absl::InvalidArgumentError(
          absl::StrCat(path, ": line ", i + 1, ": time does not increase"));
    }
    times.push_back(*t);
  }
  return times;
}

absl::StatusOr<OxtsTrack> OxtsTrackFromRecords(std::vector<OxtsRecord> records,
                                               std::vector<int64_t> time_us,
                                               std::vector<int> source_index) {
  const int n = static_cast<int>(records.size());
  if (n == 0) return absl::InvalidArgumentError("no oxts records");
  OxtsTrack track;
  track.records = std::move(records);
  track.time_us = std::move(time_us);
  track.source_index = std::move(source_index);
  const auto& recs = track.records;
  int first_valid = -1;
  for (int i = 0; i < n && first_valid < 0; ++i) {
    if (recs[i].PositionValid()) first_valid = i;
  }
  if (first_valid < 0) return absl::InvalidArgumentError("no oxts record has a valid position");
  track.origin = {recs[first_valid].lat(), recs[first_valid].lon(), recs[first_valid].alt()};
  const GeographicLib::LocalCartesian enu(track.origin.latitude_deg, track.origin.longitude_deg,
                                          track.origin.altitude_m);

  std::vector<Eigen::Vector3d> position(n, Eigen::Vector3d::Zero());
  std::vector<bool> pos_ok(n), rot_ok(n);
  for (int i = 0; i < n; ++i) {
    pos_ok[i] = recs[i].PositionValid();
    rot_ok[i] = recs[i].OrientationValid();
    if (pos_ok[i]) {
      enu.Forward(recs[i].lat(), recs[i].lon(), recs[i].alt(), position[i].x(), position[i].y(),
                  position[i].z());
    }
  }
  const auto seconds = [&](int a, int b) { return (track.time_us[b] - track.time_us[a]) * 1e-6; };

  // Positions: bridge each gap [a+1, b-1] between valid records a and b (either may be absent).
  std::vector<int> bridged_pos;
  for (int i = 0; i < n;) {
    if (pos_ok[i]) {
      ++i;
      continue;
    }
    int b = i;
    while (b < n && !pos_ok[b]) ++b;
    const int a = i - 1;  // -1 when the gap starts the log
    bool have_vel = true;
    for (int k = std::max(a, 0); k <= std::min(b, n - 1); ++k) have_vel = have_vel && recs[k].VelocityValid();
    std::vector<Eigen::Vector3d> fwd(n), bwd(n);
    if (have_vel && a >= 0) {
      fwd[a] = position[a];
      for (int k = a + 1; k < b; ++k) {
        fwd[k] = fwd[k - 1] + 0.5 * (EnuVelocity(recs[k - 1]) + EnuVelocity(recs[k])) * seconds(k - 1, k);
      }
    }
    if (have_vel && b < n) {
      bwd[b] = position[b];
      for (int k = b - 1; k > a; --k) {
        bwd[k] = bwd[k + 1] - 0.5 * (EnuVelocity(recs[k + 1]) + EnuVelocity(recs[k])) * seconds(k, k + 1);
      }
    }
    for (int k = a + 1; k < b; ++k) {
      if (a >= 0 && b < n) {
        const double w = seconds(a, k) / seconds(a, b);
        position[k] = have_vel ? (1 - w) * fwd[k] + w * bwd[k] : (1 - w) * position[a] + w * position[b];
      } else if (a >= 0) {
        position[k] = have_vel ? fwd[k] : position[a];
      } else {
        position[k] = have_vel ? bwd[k] : position[b];
      }
      bridged_pos.push_back(k);
    }
    if (!bridged_pos.empty()) {
      track.problems.push_back(absl::StrCat(
          "oxts records ", track.source_index[a + 1], "-", track.source_index[b - 1],
          ": no valid position; bridged by ",
          have_vel ? (a >= 0 && b < n ? "dead reckoning from both ends" : "dead reckoning")
                   : "linear interpolation"));
    }
    i = b;
  }

  // Orientations: slerp across gaps, hold at the ends.
  std::vector<Eigen::Quaterniond> q(n, Eigen::Quaterniond::Identity());
  std::vector<int> bridged_rot;
  for (int i = 0; i < n; ++i) {
    if (rot_ok[i]) q[i] = Eigen::Quaterniond(OxtsRotation(recs[i]));
  }
  for (int i = 0; i < n;) {
    if (rot_ok[i]) {
      ++i;
      continue;
    }
    int b = i;
    while (b < n && !rot_ok[b]) ++b;
    const int a = i - 1;
    if (a < 0 && b >= n) return absl::InvalidArgumentError("no oxts record has a valid orientation");
    for (int k = a + 1; k < b; ++k) {
      if (a >= 0 && b < n) {
        q[k] = q[a].slerp(seconds(a, k) / seconds(a, b), q[b]);
      } else {
        q[k] = a >= 0 ? q[a] : q[b];
      }
      bridged_rot.push_back(k);
    }
    track.problems.push_back(absl::StrCat("oxts records ", track.source_index[a + 1], "-",
                                          track.source_index[b - 1],
                                          ": non-finite roll/pitch/yaw; interpolated"));
    i = b;
  }

  track.T_world_from_ego.resize(n);
  for (int i = 0; i < n; ++i) {
    Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
    t.linear() = q[i].normalized().toRotationMatrix();
    t.translation() = position[i];
    track.T_world_from_ego[i] = t;
  }
  std::vector<bool> is_bridged(n, false);
  for (int k : bridged_pos) is_bridged[k] = true;
  for (int k : bridged_rot) is_bridged[k] = true;
  for (int k = 0; k < n; ++k) {
    if (is_bridged[k]) track.bridged.push_back(k);
  }
  if (!track.bridged.empty()) {
    track.problems.push_back(absl::StrCat(track.bridged.size(), " of ", n,
                                          " oxts records bridged (frames ",
                                          IndexList(track.bridged, track.source_index), ")"));
  }
  return track;
}

absl::StatusOr<OxtsTrack> ReadOxtsDirectory(const std::string& oxts_dir) {
  const std::string data_dir = (std::filesystem::path(oxts_dir) / "data").string();
  std::vector<int> indices;
  absl::StatusOr<std::vector<std::string>> files = ListNumberedFiles(data_dir, ".txt", &indices);
  if (!files.ok()) return files.status();
  if (files->empty()) return absl::NotFoundError(absl::StrCat(data_dir, ": no oxts records"));

  std::vector<std::string> problems;
  std::vector<int64_t> stamps;
  bool absolute = false;
  const std::string ts_path = (std::filesystem::path(oxts_dir) / "timestamps.txt").string();
  if (std::filesystem::exists(ts_path)) {
    absl::StatusOr<std::vector<int64_t>> ts = ReadKittiTimestamps(ts_path);
    if (!ts.ok()) return ts.status();
    stamps = *std::move(ts);
    absolute = true;
  } else {
    problems.push_back(absl::StrCat(ts_path, ": missing; 10 Hz assumed (time_us = index * 100000)"));
  }

  std::vector<OxtsRecord> records;
  std::vector<int64_t> times;
  std::vector<int> kept;
  int skipped = 0;
  for (size_t i = 0; i < files->size(); ++i) {
    const int index = indices[i];
    if (absolute && index >= static_cast<int>(stamps.size())) {
      ++skipped;
      continue;
    }
    absl::StatusOr<std::vector<std::string>> lines = ReadLines((*files)[i]);
    if (!lines.ok()) return lines.status();
    if (lines->empty() || IsBlankOrComment(lines->front())) {
      return absl::InvalidArgumentError(absl::StrCat((*files)[i], ": line 1: empty oxts record"));
    }
    absl::StatusOr<OxtsRecord> r = ParseOxtsRecord(lines->front(), (*files)[i], 1);
    if (!r.ok()) return r.status();
    records.push_back(*r);
    times.push_back(absolute ? stamps[index] : index * kAssumedFrameUs);
    kept.push_back(index);
  }
  if (skipped > 0) {
    problems.push_back(absl::StrCat(ts_path, ": ", stamps.size(), " timestamps for ", files->size(),
                                    " oxts records; ", skipped, " records without a time skipped"));
  } else if (absolute && stamps.size() > static_cast<size_t>(indices.back() + 1)) {
    problems.push_back(absl::StrCat(ts_path, ": ", stamps.size(), " timestamps for ",
                                    files->size(), " oxts records"));
  }
  for (size_t i = 1; i < kept.size(); ++i) {
    if (kept[i] != kept[i - 1] + 1) {
      problems.push_back(absl::StrCat(data_dir, ": records ", kept[i - 1] + 1, "-", kept[i] - 1, " missing"));
    }
  }
  absl::StatusOr<OxtsTrack> track = OxtsTrackFromRecords(std::move(records), std::move(times), std::move(kept));
  if (!track.ok()) return absl::InvalidArgumentError(absl::StrCat(oxts_dir, ": ", track.status().message()));
  track->time_is_absolute = absolute;
  track->problems.insert(track->problems.begin(), problems.begin(), problems.end());
  return track;
}

}  // namespace streetsim
