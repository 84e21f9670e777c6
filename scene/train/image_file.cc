#include "scene/train/image_file.h"

#include <unistd.h>

#include <filesystem>
#include <system_error>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim::train {

absl::Status WriteImageAtomic(const std::string& path, const cv::Mat& image, const std::vector<int>& params) {
  const std::filesystem::path target(path);
  const std::filesystem::path dir = target.has_parent_path() ? target.parent_path() : ".";
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat(path, ": directory ", dir.string(), " does not exist"));
  }
  // Same directory (the rename stays atomic), same extension (OpenCV picks the encoder by it).
  const std::filesystem::path tmp =
      dir / absl::StrCat(".", target.stem().string(), ".tmp", getpid(), target.extension().string());
  bool ok = false;
  try {
    ok = cv::imwrite(tmp.string(), image, params);
  } catch (const cv::Exception& e) {
    std::filesystem::remove(tmp, ec);
    return absl::InternalError(absl::StrCat(path, ": ", e.what()));
  }
  if (!ok) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
  }
  std::filesystem::rename(tmp, target, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place: ", ec.message()));
  }
  return absl::OkStatus();
}

}  // namespace streetsim::train
