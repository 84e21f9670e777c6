#include "scene/init/lidar_accumulation.h"

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "scene/init/voxel_grid.h"

namespace streetsim {

std::vector<int> FrameRange::Select(const DriveLog& log) const {
  const int n = static_cast<int>(log.frames.size());
  const int end = last < 0 ? n : std::min(n, last);
  std::vector<int> out;
  for (int f = std::max(0, first); f < end; f += std::max(1, stride)) out.push_back(f);
  return out;
}

absl::StatusOr<FrameRange> ParseFrameRange(const std::string& text) {
  const std::vector<std::string> parts = absl::StrSplit(text, ':');
  const auto bad = [&] {
    return absl::InvalidArgumentError(absl::StrCat("--frames '", text, "': expected A:B or A:B:STRIDE"));
  };
  if (parts.size() < 2 || parts.size() > 3) return bad();
  FrameRange r;
  int* fields[3] = {&r.first, &r.last, &r.stride};
  for (size_t i = 0; i < parts.size(); ++i) {
    if (parts[i].empty()) continue;
    if (!absl::SimpleAtoi(parts[i], fields[i]) || *fields[i] < 0) return bad();
  }
  if (r.stride < 1 || (r.last >= 0 && r.last <= r.first)) return bad();
  return r;
}

absl::StatusOr<AccumulatedCloud> AccumulateLidar(const DriveLog& log, const AccumulationOptions& options) {
  if (log.lidars.empty()) return absl::FailedPreconditionError(absl::StrCat(log.root, ": log has no LiDAR"));
  VoxelGrid grid(options.voxel_m);
  AccumulatedCloud out;
  const float lo = static_cast<float>(options.min_range_m * options.min_range_m);
  const float hi = static_cast<float>(options.max_range_m * options.max_range_m);
  for (int f : options.frames.Select(log)) {
    for (const LidarObservation& obs : log.frames[f].lidars) {
      absl::StatusOr<LidarScan> scan = LoadLidarScan(obs.path);
      if (!scan.ok()) return scan.status();
      std::vector<uint8_t> dynamic;
      if (options.drop_dynamic && obs.lidar == 0) {
        absl::StatusOr<DynamicMask> mask = ComputeDynamicMask(log, f, options.dynamic);
        if (mask.ok()) dynamic = std::move(mask->dynamic);
      }
      const Eigen::Isometry3d T_world_from_lidar = log.frames[f].T_world_from_ego * log.lidars[obs.lidar].T_ego_from_lidar;
      for (size_t i = 0; i < scan->points.size(); ++i) {
        const Eigen::Vector3f& p = scan->points[i];
        const float r2 = p.squaredNorm();
        if (r2 < lo || r2 > hi) continue;
        if (!dynamic.empty() && dynamic[i]) {
          ++out.dynamic_dropped;
          continue;
        }
        grid.Add(T_world_from_lidar * p.cast<double>(), scan->reflectance[i]);
        ++out.raw_points;
      }
    }
    ++out.frames_used;
  }
  grid.Extract(1, &out.points, &out.reflectance);
  return out;
}

}  // namespace streetsim
