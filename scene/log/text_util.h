// Small text-parsing helpers shared by the log readers. Every error names the file and, where
// there is one, the 1-based line: "<path>: line 12: expected 30 values, got 29".
#pragma once

#include <map>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"

namespace streetsim {

// Whole file as bytes; NotFound when absent, PermissionDenied/DataLoss when unreadable.
absl::StatusOr<std::string> ReadTextFile(const std::string& path);

// Lines of a file without their terminators (a trailing empty line is dropped).
absl::StatusOr<std::vector<std::string>> ReadLines(const std::string& path);

// Whitespace-separated numbers of one line. NaN/inf are accepted (callers decide); anything that
// is not a number is an error. expected < 0: any count.
absl::StatusOr<std::vector<double>> ParseNumbers(const std::string& text, const std::string& path,
                                                 int line_number, int expected = -1);

// True when the line is empty or a comment ('#').
bool IsBlankOrComment(const std::string& line);

// A rigid transform from a row-major 3x3 rotation and a translation. The rotation is projected
// onto SO(3) (calibration files print ~7 digits, which is not orthonormal to 1e-6); a matrix further
// than `tolerance` (Frobenius) from a rotation, or non-finite values, is an error naming `where`.
absl::StatusOr<Eigen::Isometry3d> RigidFromRowMajor(const double* rotation9,
                                                    const Eigen::Vector3d& translation,
                                                    const std::string& where,
                                                    double tolerance = 1e-3);
// Same from a row-major 3x4 [R | t].
absl::StatusOr<Eigen::Isometry3d> RigidFrom3x4(const std::vector<double>& values12,
                                               const std::string& where, double tolerance = 1e-3);

// "key: v1 v2 ..." files (KITTI calibration). Values that are not numbers (calib_time dates) are
// kept out of `numbers`; `line` is 1-based for error messages.
struct CalibEntry {
  std::vector<double> numbers;
  int line = 0;
};
struct CalibFile {
  std::string path;
  std::map<std::string, CalibEntry> entries;
  // The entry with exactly `count` finite numbers, else an error naming file, line and key.
  absl::StatusOr<std::vector<double>> Get(const std::string& key, int count) const;
};
absl::StatusOr<CalibFile> ReadCalibFile(const std::string& path);

// "2011-09-26 13:04:32.349659788" -> UNIX microseconds (UTC; sub-microsecond digits truncated).
absl::StatusOr<int64_t> ParseKittiTimestamp(const std::string& text, const std::string& path,
                                            int line_number);

// Sorted numbered files (e.g. 0000000012.png) of a directory with the given extension; the number
// of each goes to *indices. Files whose stem is not a number are ignored.
absl::StatusOr<std::vector<std::string>> ListNumberedFiles(const std::string& dir,
                                                           const std::string& extension,
                                                           std::vector<int>* indices);

}  // namespace streetsim
