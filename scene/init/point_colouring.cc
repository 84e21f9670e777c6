#include "scene/init/point_colouring.h"

#include <cmath>
#include <limits>

#include "scene/log/undistort.h"

namespace streetsim {
namespace {

Eigen::Vector3f SampleBilinear(const cv::Mat& rgb, double u, double v) {
  const int u0 = static_cast<int>(std::floor(u)), v0 = static_cast<int>(std::floor(v));
  const int u1 = std::min(u0 + 1, rgb.cols - 1), v1 = std::min(v0 + 1, rgb.rows - 1);
  const float a = static_cast<float>(u - u0), b = static_cast<float>(v - v0);
  const auto px = [&](int x, int y) {
    const cv::Vec3b c = rgb.at<cv::Vec3b>(y, std::max(0, x));
    return Eigen::Vector3f(c[0], c[1], c[2]);
  };
  return ((1 - a) * (1 - b) * px(u0, v0) + a * (1 - b) * px(u1, v0) + (1 - a) * b * px(u0, v1) +
          a * b * px(u1, v1)) / 255.0f;
}

}  // namespace

absl::StatusOr<PointColours> ColourPoints(const DriveLog& log, const std::vector<Eigen::Vector3f>& points,
                                          const ColouringOptions& options) {
  PointColours out;
  out.rgb.assign(points.size(), Eigen::Vector3f::Zero());
  out.views.assign(points.size(), 0);
  std::vector<Eigen::Vector2f> uv(points.size());
  std::vector<float> depth(points.size());
  for (int f : options.frames.Select(log)) {
    for (const CameraObservation& obs : log.frames[f].cameras) {
      const CameraIntrinsics& k = log.cameras[obs.camera].intrinsics;
      absl::StatusOr<cv::Mat> image = LoadImageRgb(obs.path);
      if (!image.ok()) return image.status();
      if (!k.IsPinhole()) {
        // Sampling the pinhole-resampled image keeps colours consistent with the pinhole renderer.
        absl::StatusOr<cv::Mat> undistorted = UndistortImage(*image, k);
        if (!undistorted.ok()) return undistorted.status();
        *image = *undistorted;
      }
      const Eigen::Isometry3f T_cam_from_world = WorldFromCamera(log, log.frames[f], obs).inverse().cast<float>();
      const int cw = (k.width + options.cell_px - 1) / options.cell_px;
      const int ch = (k.height + options.cell_px - 1) / options.cell_px;
      std::vector<float> zbuf(static_cast<size_t>(cw) * ch, std::numeric_limits<float>::infinity());
      const float fx = static_cast<float>(k.fx), fy = static_cast<float>(k.fy);
      const float cx = static_cast<float>(k.cx), cy = static_cast<float>(k.cy);
      for (size_t i = 0; i < points.size(); ++i) {
        const Eigen::Vector3f c = T_cam_from_world * points[i];
        depth[i] = -1;
        if (c.z() < options.min_depth_m) continue;
        const float u = fx * c.x() / c.z() + cx, v = fy * c.y() / c.z() + cy;
        if (u < 0 || v < 0 || u > k.width - 1 || v > k.height - 1) continue;
        uv[i] = {u, v};
        depth[i] = c.z();
        float& z = zbuf[static_cast<size_t>(v / options.cell_px) * cw + static_cast<size_t>(u / options.cell_px)];
        z = std::min(z, c.z());
      }
      for (size_t i = 0; i < points.size(); ++i) {
        if (depth[i] < 0) continue;
        const float nearest = zbuf[static_cast<size_t>(uv[i].y() / options.cell_px) * cw +
                                   static_cast<size_t>(uv[i].x() / options.cell_px)];
        if (depth[i] > nearest * (1 + options.hidden_rel) + options.hidden_abs_m) continue;
        out.rgb[i] += SampleBilinear(*image, uv[i].x(), uv[i].y());
        ++out.views[i];
      }
    }
  }
  for (size_t i = 0; i < points.size(); ++i) {
    if (out.views[i] > 0) out.rgb[i] /= static_cast<float>(out.views[i]);
  }
  return out;
}

}  // namespace streetsim
