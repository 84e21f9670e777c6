#include "scene/log/open_log.h"

#include <filesystem>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "scene/log/colmap_reader.h"
#include "scene/log/kitti_odometry_reader.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;

bool IsKittiRawDrive(const fs::path& d) {
  for (const char* sub : {"image_00", "image_01", "image_02", "image_03", "velodyne_points", "oxts"}) {
    if (fs::is_directory(d / sub / "data")) return true;
  }
  return false;
}

bool IsKittiOdometry(const fs::path& d) {
  if (!fs::exists(d / "calib.txt")) return false;
  for (const char* sub : {"image_0", "image_1", "image_2", "image_3", "image_l", "image_r"}) {
    if (fs::is_directory(d / sub)) return true;
  }
  return false;
}

bool IsColmap(const fs::path& d) {
  if (fs::exists(d / "cameras.txt") || fs::exists(d / "cameras.bin")) return true;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(d, ec)) {
    if (!e.is_directory()) continue;
    const fs::path p = e.path();
    if (!absl::StartsWith(p.filename().string(), "sparse")) continue;
    if (fs::exists(p / "cameras.txt") || fs::exists(p / "cameras.bin") ||
        fs::exists(p / "0" / "cameras.txt") || fs::exists(p / "0" / "cameras.bin")) {
      return true;
    }
  }
  return false;
}

}  // namespace

absl::StatusOr<std::string> DetectLogFormat(const std::string& path, std::string* resolved_dir) {
  std::error_code ec;
  fs::path dir(path);
  if (!fs::exists(dir, ec)) return absl::NotFoundError(absl::StrCat(path, ": no such file or directory"));
  if (!fs::is_directory(dir, ec)) return absl::InvalidArgumentError(absl::StrCat(path, ": not a log directory"));
  while (dir.has_filename() == false && dir.has_parent_path() && dir != dir.parent_path()) dir = dir.parent_path();
  // <drive>/oxts: the drive is the parent.
  if (dir.filename() == "oxts" && fs::is_directory(dir / "data")) dir = dir.parent_path();
  *resolved_dir = dir.string();
  if (IsKittiRawDrive(dir)) return std::string("kitti_raw");
  if (IsKittiOdometry(dir)) return std::string("kitti_odometry");
  if (IsColmap(dir)) return std::string("colmap");
  // A KITTI raw day folder: <date>/<date>_drive_NNNN_sync.
  std::vector<std::string> drives;
  for (const auto& e : fs::directory_iterator(dir, ec)) {
    if (e.is_directory() && IsKittiRawDrive(e.path())) drives.push_back(e.path().filename().string());
  }
  std::sort(drives.begin(), drives.end());
  if (drives.size() == 1) {
    *resolved_dir = (dir / drives[0]).string();
    return std::string("kitti_raw");
  }
  if (drives.size() > 1) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": holds ", drives.size(),
                                                   " KITTI drives, name one: ", absl::StrJoin(drives, ", ")));
  }
  return absl::InvalidArgumentError(absl::StrCat(
      path, ": not a recognised log (KITTI raw drive, KITTI odometry sequence or COLMAP model)"));
}

absl::StatusOr<DriveLog> OpenLog(const std::string& path, const OpenLogOptions& options) {
  std::string dir;
  absl::StatusOr<std::string> format = DetectLogFormat(path, &dir);
  if (!format.ok()) return format.status();
  if (*format == "kitti_raw") return ReadKittiRaw(dir, {options.pose_source});
  if (*format == "kitti_odometry") return ReadKittiOdometry(dir);
  return ReadColmapProject(dir);
}

}  // namespace streetsim
