#include "scene/init/initial_scene.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>

#include "absl/strings/str_cat.h"
#include "scene/init/knn_scales.h"
#include "scene/init/point_colouring.h"
#include "scene/init/triangulated_points.h"
#include "scene/log/undistort.h"

namespace streetsim {
namespace {

constexpr double kShC0 = 0.28209479177387814;  // SH DC basis: colour = kShC0 * dc + 0.5

// Fibonacci sphere: near-uniform directions.
std::vector<Eigen::Vector3f> SpherePoints(const Eigen::Vector3d& centre, double radius, int n) {
  std::vector<Eigen::Vector3f> out;
  out.reserve(n);
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < n; ++i) {
    const double z = 1 - 2 * (i + 0.5) / n;
    const double r = std::sqrt(1 - z * z);
    const double a = golden * i;
    out.push_back((centre + radius * Eigen::Vector3d(r * std::cos(a), r * std::sin(a), z)).cast<float>());
  }
  return out;
}

absl::Status RandomFrustumPoints(const DriveLog& log, const InitOptions& options,
                                 std::vector<Eigen::Vector3f>* points, std::vector<Eigen::Vector3f>* rgb) {
  const std::vector<int> frames = options.frames.Select(log);
  if (frames.empty()) return absl::InvalidArgumentError("no frames selected");
  std::mt19937 rng(options.seed);
  const int per_frame = std::max(1, options.random_points / static_cast<int>(frames.size()));
  for (int f : frames) {
    for (const CameraObservation& obs : log.frames[f].cameras) {
      absl::StatusOr<cv::Mat> image = LoadImageRgb(obs.path);
      if (!image.ok()) return image.status();
      const CameraIntrinsics& k = log.cameras[obs.camera].intrinsics;
      if (!k.IsPinhole()) {
        absl::StatusOr<cv::Mat> u = UndistortImage(*image, k);
        if (!u.ok()) return u.status();
        *image = *u;
      }
      const Eigen::Isometry3d T_world_from_cam = WorldFromCamera(log, log.frames[f], obs);
      std::uniform_real_distribution<double> uu(0, k.width - 1), vv(0, k.height - 1);
      // Uniform in inverse depth: as many points per pixel near as far, like the image itself.
      std::uniform_real_distribution<double> inv(1.0 / options.random_max_depth_m, 1.0 / options.random_min_depth_m);
      for (int i = 0; i < per_frame; ++i) {
        const double u = uu(rng), v = vv(rng), z = 1.0 / inv(rng);
        const Eigen::Vector3d c((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z);
        points->push_back((T_world_from_cam * c).cast<float>());
        const cv::Vec3b px = image->at<cv::Vec3b>(static_cast<int>(std::lround(v)), static_cast<int>(std::lround(u)));
        rgb->push_back(Eigen::Vector3f(px[0], px[1], px[2]) / 255.0f);
      }
    }
  }
  return absl::OkStatus();
}

// A camera-only log without sparse points: points triangulated from its images with its own poses,
// or random points in the frusta where too few triangulate (a camera that barely moves, poses that
// do not fit). Not both: random points beside the triangulated ones cost the odometry excerpt's
// static model 3-11 dB held-out (docs/logs.md "Initial scene").
absl::Status CameraOnlyPoints(const DriveLog& log, const InitOptions& options, InitStats* st,
                              std::vector<Eigen::Vector3f>* points, std::vector<Eigen::Vector3f>* rgb) {
  TriangulationOptions tri;
  tri.frames = options.frames;
  tri.voxel_m = options.voxel_m;
  absl::StatusOr<TriangulatedPoints> found = TriangulateWithKnownPoses(log, tri);
  if (!found.ok()) return found.status();
  if (found->points.size() >= static_cast<size_t>(options.min_triangulated_points)) {
    st->source = "triangulated";
    st->notes.push_back(absl::StrCat("camera-only log without sparse points: ", found->points.size(),
                                     " points triangulated with the log's poses (", found->triangulated, " of ",
                                     found->matches, " feature matches in ", found->image_pairs, " image pairs)"));
    *points = std::move(found->points);
    *rgb = std::move(found->rgb);
  } else {
    st->source = "random_frusta";
    st->notes.push_back(absl::StrCat("camera-only log without sparse points: ", found->points.size(),
                                     " points triangulated (too few: a camera that barely moves, or poses that do not "
                                     "fit the images); ",
                                     options.random_points, " random points in the camera frusta (depth ",
                                     options.random_min_depth_m, "-", options.random_max_depth_m,
                                     " m), coloured by their pixel"));
    if (absl::Status s = RandomFrustumPoints(log, options, points, rgb); !s.ok()) return s;
  }
  st->frames_used = static_cast<int>(options.frames.Select(log).size());
  st->seen = points->size();
  return absl::OkStatus();
}

}  // namespace

GaussianStore GaussiansFromPoints(const std::vector<Eigen::Vector3f>& points,
                                  const std::vector<Eigen::Vector3f>& rgb, float opacity,
                                  double* median_scale_m) {
  GaussianStore store;
  store.sh_degree = 0;
  store.Resize(points.size());
  const std::vector<float> log_scales = KnnLogScales(points);
  const float logit = std::log(opacity / (1 - opacity));
  for (size_t i = 0; i < points.size(); ++i) {
    for (int c = 0; c < 3; ++c) {
      store.means[i * 3 + c] = points[i][c];
      store.log_scales[i * 3 + c] = log_scales[i];
      store.sh[i * 3 + c] = static_cast<float>((std::clamp(rgb[i][c], 0.0f, 1.0f) - 0.5) / kShC0);
    }
    store.rotations[i * 4 + 0] = 1;
    store.rotations[i * 4 + 1] = store.rotations[i * 4 + 2] = store.rotations[i * 4 + 3] = 0;
    store.opacity_logits[i] = logit;
  }
  if (median_scale_m && !log_scales.empty()) {
    std::vector<float> s = log_scales;
    std::nth_element(s.begin(), s.begin() + s.size() / 2, s.end());
    *median_scale_m = std::exp(s[s.size() / 2]);
  }
  return store;
}

absl::StatusOr<GaussianStore> BuildInitialScene(const DriveLog& log, const InitOptions& options, InitStats* stats) {
  const auto start = std::chrono::steady_clock::now();
  InitStats local;
  InitStats& st = stats ? *stats : local;
  st = InitStats();
  if (!(options.opacity > 0 && options.opacity < 1)) return absl::InvalidArgumentError("opacity must be in (0, 1)");
  if (options.frames.Select(log).empty()) return absl::InvalidArgumentError("no frames selected");
  std::vector<Eigen::Vector3f> points, rgb;
  if (!log.lidars.empty()) {
    st.source = "lidar";
    AccumulationOptions acc;
    acc.frames = options.frames;
    acc.voxel_m = options.voxel_m;
    acc.max_range_m = options.max_range_m;
    acc.drop_dynamic = options.drop_dynamic;
    absl::StatusOr<AccumulatedCloud> cloud = AccumulateLidar(log, acc);
    if (!cloud.ok()) return cloud.status();
    st.frames_used = cloud->frames_used;
    st.lidar_points_raw = cloud->raw_points;
    st.voxels = cloud->points.size();
    if (cloud->dynamic_dropped > 0) st.notes.push_back(absl::StrCat(cloud->dynamic_dropped, " dynamic LiDAR points dropped"));
    size_t num_lidar = cloud->points.size();
    std::vector<Eigen::Vector3f> candidates = std::move(cloud->points);
    if (options.sky) {
      Eigen::Vector3d centre = Eigen::Vector3d::Zero();
      const std::vector<int> frames = options.frames.Select(log);
      for (int f : frames) centre += log.frames[f].T_world_from_ego.translation();
      centre /= frames.size();
      const double radius = options.sky_radius_m > 0 ? options.sky_radius_m : 2 * options.max_range_m;
      for (const Eigen::Vector3f& p : SpherePoints(centre, radius, options.sky_points)) candidates.push_back(p);
    }
    ColouringOptions col;
    col.frames = options.frames;
    absl::StatusOr<PointColours> colours = ColourPoints(log, candidates, col);
    if (!colours.ok()) return colours.status();
    for (size_t i = 0; i < candidates.size(); ++i) {
      if (colours->views[i] == 0) continue;  // no camera sees it: nothing to say about its colour
      points.push_back(candidates[i]);
      rgb.push_back(colours->rgb[i]);
      if (i < num_lidar) {
        ++st.seen;
      } else {
        ++st.sky_points;
      }
    }
  } else if (!log.sparse_points.empty()) {
    st.source = "colmap_points";
    for (size_t i = 0; i < log.sparse_points.size(); ++i) {
      points.push_back(log.sparse_points[i].cast<float>());
      rgb.push_back(log.sparse_colours[i].cast<float>() / 255.0f);
    }
    st.seen = points.size();
  } else {
    if (absl::Status s = CameraOnlyPoints(log, options, &st, &points, &rgb); !s.ok()) return s;
  }
  if (points.empty()) return absl::FailedPreconditionError("no point is seen by any camera");
  GaussianStore store = GaussiansFromPoints(points, rgb, options.opacity, &st.median_scale_m);
  st.gaussians = store.size();
  st.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  return store;
}

}  // namespace streetsim
