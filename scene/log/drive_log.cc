#include "scene/log/drive_log.h"

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim {

const char* DistortionModelName(DistortionModel model) {
  switch (model) {
    case DistortionModel::kNone: return "pinhole";
    case DistortionModel::kSimpleRadial: return "simple_radial";
    case DistortionModel::kRadial: return "radial";
    case DistortionModel::kOpenCv: return "opencv";
  }
  return "unknown";
}

std::vector<double> CameraIntrinsics::OpenCvCoefficients() const {
  std::vector<double> k(4, 0.0);
  switch (model) {
    case DistortionModel::kNone: break;
    case DistortionModel::kSimpleRadial: k[0] = distortion.at(0); break;
    case DistortionModel::kRadial: k[0] = distortion.at(0); k[1] = distortion.at(1); break;
    case DistortionModel::kOpenCv: k = distortion; break;
  }
  return k;
}

int64_t DriveLog::duration_us() const {
  return frames.size() < 2 ? 0 : frames.back().time_us - frames.front().time_us;
}

double DriveLog::distance_m() const {
  double d = 0;
  for (size_t i = 1; i < frames.size(); ++i) {
    d += (frames[i].T_world_from_ego.translation() - frames[i - 1].T_world_from_ego.translation()).norm();
  }
  return d;
}

absl::StatusOr<cv::Mat> LoadImageRgb(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat(path, ": no such image"));
  }
  cv::Mat image;
  try {
    image = cv::imread(path, cv::IMREAD_COLOR);  // BGR, grayscale expanded to 3 channels
    if (image.empty()) return absl::DataLossError(absl::StrCat(path, ": cannot decode image"));
    cv::cvtColor(image, image, cv::COLOR_BGR2RGB);
  } catch (const cv::Exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
  return image;
}

absl::StatusOr<LidarScan> LoadLidarScan(const std::string& path, size_t* dropped) {
  std::error_code ec;
  const auto size = std::filesystem::file_size(path, ec);
  if (ec) return absl::NotFoundError(absl::StrCat(path, ": no such LiDAR scan"));
  if (size % 16 != 0) {
    return absl::DataLossError(absl::StrCat(path, ": ", size,
                                            " bytes is not a whole number of 16-byte points (truncated?)"));
  }
  if (size == 0) return absl::DataLossError(absl::StrCat(path, ": empty LiDAR scan"));
  std::vector<float> raw(size / 4);
  std::ifstream in(path, std::ios::binary);
  if (!in.read(reinterpret_cast<char*>(raw.data()), static_cast<std::streamsize>(size))) {
    return absl::DataLossError(absl::StrCat(path, ": read error"));
  }
  LidarScan scan;
  const size_t n = size / 16;
  scan.points.reserve(n);
  scan.reflectance.reserve(n);
  size_t bad = 0;
  for (size_t i = 0; i < n; ++i) {
    const float* p = &raw[i * 4];
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
      ++bad;
      continue;
    }
    scan.points.emplace_back(p[0], p[1], p[2]);
    scan.reflectance.push_back(std::isfinite(p[3]) ? p[3] : 0.0f);
  }
  if (dropped) *dropped = bad;
  return scan;
}

}  // namespace streetsim
