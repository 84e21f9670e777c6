#include "scene/train/dynamic_pixels.h"

#include <algorithm>
#include <cmath>
#include <map>

#include "scene/init/dynamic_mask.h"

namespace streetsim::train {

absl::Status AttachDynamicPixels(const DriveLog& log, std::vector<View>* views, int dilate_px) {
  std::map<int, std::vector<Eigen::Vector3d>> world_by_frame;  // the flagged points, world frame
  for (View& v : *views) {
    if (v.frame < 0 || v.frame >= static_cast<int>(log.frames.size())) continue;
    const Frame& fr = log.frames[v.frame];
    if (fr.lidars.empty() || log.lidars.empty()) continue;
    auto it = world_by_frame.find(v.frame);
    if (it == world_by_frame.end()) {
      absl::StatusOr<DynamicMask> mask = ComputeDynamicMask(log, v.frame);
      // No neighbouring scan (a short log): nothing can be judged, the view gets no mask.
      if (absl::IsFailedPrecondition(mask.status())) continue;
      if (!mask.ok()) return mask.status();
      absl::StatusOr<LidarScan> scan = LoadLidarScan(fr.lidars[0].path);
      if (!scan.ok()) return scan.status();
      if (scan->points.size() != mask->dynamic.size()) {
        return absl::InternalError("dynamic mask and scan disagree in size");
      }
      const Eigen::Isometry3d T_world_from_lidar = fr.T_world_from_ego * log.lidars[fr.lidars[0].lidar].T_ego_from_lidar;
      std::vector<Eigen::Vector3d> pts;
      for (size_t i = 0; i < scan->points.size(); ++i) {
        if (mask->dynamic[i]) pts.push_back(T_world_from_lidar * scan->points[i].cast<double>());
      }
      it = world_by_frame.emplace(v.frame, std::move(pts)).first;
    }
    const int W = v.camera.width, H = v.camera.height;
    v.dynamic_pixels.assign(static_cast<size_t>(W) * H, 0);
    const Eigen::Isometry3d T_cam_from_world = v.camera.T_world_from_cam.inverse();
    for (const Eigen::Vector3d& pw : it->second) {
      const Eigen::Vector3d p = T_cam_from_world * pw;
      if (!(p.z() > 0.2)) continue;
      const long u = std::lround(v.camera.fx * p.x() / p.z() + v.camera.cx);
      const long w = std::lround(v.camera.fy * p.y() / p.z() + v.camera.cy);
      for (long y = std::max(0L, w - dilate_px); y <= std::min<long>(H - 1, w + dilate_px); ++y)
        for (long x = std::max(0L, u - dilate_px); x <= std::min<long>(W - 1, u + dilate_px); ++x)
          v.dynamic_pixels[static_cast<size_t>(y) * W + x] = 1;
    }
  }
  return absl::OkStatus();
}

double MaskedPsnr(const float* rendered, const float* gt, const std::vector<uint8_t>& mask, uint8_t want) {
  double se = 0;
  size_t n = 0;
  for (size_t p = 0; p < mask.size(); ++p) {
    if (mask[p] != want) continue;
    for (int c = 0; c < 3; ++c) {
      const double d = static_cast<double>(rendered[p * 3 + c]) - gt[p * 3 + c];
      se += d * d;
    }
    n += 3;
  }
  if (n == 0) return -1;
  const double mse = se / n;
  return mse > 0 ? 10 * std::log10(1.0 / mse) : 100.0;
}

}  // namespace streetsim::train
