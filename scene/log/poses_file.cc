#include "scene/log/poses_file.h"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "scene/log/text_util.h"

namespace streetsim {

absl::StatusOr<std::vector<Eigen::Isometry3d>> ReadPosesFile(const std::string& path) {
  absl::StatusOr<std::vector<std::string>> lines = ReadLines(path);
  if (!lines.ok()) return lines.status();
  std::vector<Eigen::Isometry3d> poses;
  for (size_t i = 0; i < lines->size(); ++i) {
    if (IsBlankOrComment((*lines)[i])) continue;
    const int line_number = static_cast<int>(i + 1);
    absl::StatusOr<std::vector<double>> v = ParseNumbers((*lines)[i], path, line_number, 12);
    if (!v.ok()) return v.status();
    absl::StatusOr<Eigen::Isometry3d> t = RigidFrom3x4(*v, absl::StrCat(path, ": line ", line_number));
    if (!t.ok()) return t.status();
    poses.push_back(*t);
  }
  if (poses.empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no poses"));
  return poses;
}

absl::Status WritePosesFile(const std::string& path, const std::vector<Eigen::Isometry3d>& poses,
                            const std::string& comment) {
  const std::filesystem::path target(path);
  std::error_code ec;
  const std::filesystem::path dir = target.has_parent_path() ? target.parent_path() : ".";
  if (!std::filesystem::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat(path, ": directory ", dir.string(), " does not exist"));
  }
  const std::filesystem::path tmp = dir / absl::StrCat(".", target.filename().string(), ".tmp", getpid());
  {
    std::ofstream out(tmp);
    if (!out) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
    if (!comment.empty()) out << "# " << comment << "\n";
    char buf[64];
    for (const Eigen::Isometry3d& t : poses) {
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 4; ++c) {
          std::snprintf(buf, sizeof(buf), "%.9f", t.matrix()(r, c));
          out << buf << (r == 2 && c == 3 ? "\n" : " ");
        }
      }
    }
    if (!out) {
      std::filesystem::remove(tmp, ec);
      return absl::DataLossError(absl::StrCat(path, ": write failed"));
    }
  }
  std::filesystem::rename(tmp, target, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place"));
  }
  return absl::OkStatus();
}

}  // namespace streetsim
