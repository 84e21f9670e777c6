#include "client/cli/image_io.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "scene/train/image_file.h"

namespace streetsim {
namespace {

std::string Extension(const std::string& path) {
  return absl::AsciiStrToLower(std::filesystem::path(path).extension().string());
}

absl::Status WriteAtomically(const std::string& path, const cv::Mat& image,
                             const std::vector<int>& params) {
  const std::filesystem::path target(path);
  if (target.filename().empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": not a file name"));
  std::error_code ec;
  if (std::filesystem::is_directory(target, ec)) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": is a directory"));
  }
  return train::WriteImageAtomic(path, image, params);
}

}  // namespace

absl::Status WriteRgb8(const std::string& path, int width, int height, const std::vector<float>& rgb) {
  const std::string ext = Extension(path);
  if (ext != ".png" && ext != ".jpg" && ext != ".jpeg") {
    return absl::InvalidArgumentError(absl::StrCat(path, ": RGB output must be .png, .jpg or .jpeg"));
  }
  if (rgb.size() != static_cast<size_t>(width) * height * 3) {
    return absl::InternalError("RGB buffer size does not match the image size");
  }
  cv::Mat bgr(height, width, CV_8UC3);
  for (int v = 0; v < height; ++v) {
    uint8_t* row = bgr.ptr<uint8_t>(v);
    for (int u = 0; u < width; ++u) {
      const float* px = &rgb[(static_cast<size_t>(v) * width + u) * 3];
      for (int c = 0; c < 3; ++c) {
        const float x = std::clamp(px[c], 0.0f, 1.0f);  // NaN would clamp oddly; renders are finite
        row[u * 3 + (2 - c)] = static_cast<uint8_t>(std::lround(x * 255.0f));
      }
    }
  }
  std::vector<int> params;
  if (ext != ".png") params = {cv::IMWRITE_JPEG_QUALITY, 95};
  return WriteAtomically(path, bgr, params);
}

absl::Status WriteFloatTiff(const std::string& path, int width, int height,
                            const std::vector<float>& values) {
  const std::string ext = Extension(path);
  if (ext != ".tif" && ext != ".tiff") {
    return absl::InvalidArgumentError(absl::StrCat(path, ": float output must be .tif or .tiff"));
  }
  if (values.size() != static_cast<size_t>(width) * height) {
    return absl::InternalError("float buffer size does not match the image size");
  }
  const cv::Mat image(height, width, CV_32FC1, const_cast<float*>(values.data()));
  return WriteAtomically(path, image, {});
}

}  // namespace streetsim
