#include "scene/log/undistort.h"

#include <algorithm>

#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim {

Eigen::Vector2d DistortNormalized(const CameraIntrinsics& k, const Eigen::Vector2d& xy) {
  if (k.model == DistortionModel::kNone) return xy;
  const std::vector<double> c = k.OpenCvCoefficients();  // k1, k2, p1, p2
  const double x = xy.x(), y = xy.y();
  const double r2 = x * x + y * y;
  const double radial = 1 + c[0] * r2 + c[1] * r2 * r2;
  return {x * radial + 2 * c[2] * x * y + c[3] * (r2 + 2 * x * x),
          y * radial + c[2] * (r2 + 2 * y * y) + 2 * c[3] * x * y};
}

bool ProjectToPixel(const CameraIntrinsics& k, const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv) {
  if (p_cam.z() <= 1e-6) return false;
  const Eigen::Vector2d d = DistortNormalized(k, p_cam.head<2>() / p_cam.z());
  *uv = {k.fx * d.x() + k.cx, k.fy * d.y() + k.cy};
  return true;
}

absl::StatusOr<cv::Mat> UndistortImage(const cv::Mat& image, const CameraIntrinsics& k) {
  if (k.IsPinhole()) return image;
  if (image.cols != k.width || image.rows != k.height) {
    return absl::InvalidArgumentError(absl::StrCat("image is ", image.cols, "x", image.rows,
                                                   ", camera is ", k.width, "x", k.height));
  }
  cv::Mat map_x(image.rows, image.cols, CV_32FC1), map_y(image.rows, image.cols, CV_32FC1);
  for (int v = 0; v < image.rows; ++v) {
    float* mx = map_x.ptr<float>(v);
    float* my = map_y.ptr<float>(v);
    for (int u = 0; u < image.cols; ++u) {
      const Eigen::Vector2d d = DistortNormalized(k, {(u - k.cx) / k.fx, (v - k.cy) / k.fy});
      mx[u] = static_cast<float>(k.fx * d.x() + k.cx);
      my[u] = static_cast<float>(k.fy * d.y() + k.cy);
    }
  }
  cv::Mat out;
  try {
    cv::remap(image, out, map_x, map_y, cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar::all(0));
  } catch (const cv::Exception& e) {
    return absl::InternalError(absl::StrCat("undistort: ", e.what()));
  }
  return out;
}

cv::Rect ValidUndistortedRect(const CameraIntrinsics& k) {
  cv::Rect r(0, 0, k.width, k.height);
  if (k.IsPinhole() || k.width <= 0 || k.height <= 0) return r;
  // valid(u, v): the source position UndistortImage samples for output pixel (u, v) lies inside.
  std::vector<uint8_t> valid(static_cast<size_t>(k.width) * k.height);
  for (int v = 0; v < k.height; ++v) {
    for (int u = 0; u < k.width; ++u) {
      const Eigen::Vector2d d = DistortNormalized(k, {(u - k.cx) / k.fx, (v - k.cy) / k.fy});
      const double x = k.fx * d.x() + k.cx, y = k.fy * d.y() + k.cy;
      valid[static_cast<size_t>(v) * k.width + u] = x >= 0 && x <= k.width - 1 && y >= 0 && y <= k.height - 1;
    }
  }
  auto at = [&](int u, int v) { return valid[static_cast<size_t>(v) * k.width + u] != 0; };
  while (r.width > 0 && r.height > 0) {
    int bad[4] = {0, 0, 0, 0};  // top, bottom, left, right edge of r
    for (int u = r.x; u < r.x + r.width; ++u) {
      bad[0] += !at(u, r.y);
      bad[1] += !at(u, r.y + r.height - 1);
    }
    for (int v = r.y; v < r.y + r.height; ++v) {
      bad[2] += !at(r.x, v);
      bad[3] += !at(r.x + r.width - 1, v);
    }
    const int worst = static_cast<int>(std::max_element(bad, bad + 4) - bad);
    if (bad[worst] == 0) break;
    if (worst == 0) { ++r.y; --r.height; }
    else if (worst == 1) { --r.height; }
    else if (worst == 2) { ++r.x; --r.width; }
    else { --r.width; }
  }
  return r;
}

CameraIntrinsics CroppedPinhole(const CameraIntrinsics& k) {
  if (k.IsPinhole()) return k;
  const cv::Rect r = ValidUndistortedRect(k);
  CameraIntrinsics out;
  out.width = r.width;
  out.height = r.height;
  out.fx = k.fx;
  out.fy = k.fy;
  out.cx = k.cx - r.x;
  out.cy = k.cy - r.y;
  return out;
}

}  // namespace streetsim
