// The initial Gaussian scene of a log, from its own measurements only:
//   LiDAR logs: LiDAR accumulated in the world (lidar_accumulation.h), kept where a camera sees
//     it and coloured from the images (point_colouring.h); optionally far-background points on a
//     sphere beyond the LiDAR range, kept only where the images show background (sky).
//   Camera-only logs: the log's sparse points (COLMAP points3D) when present, else points
//     triangulated from the images with the log's poses (triangulated_points.h), else (too few
//     triangulate) random points in the camera frusta coloured by the pixel they were drawn
//     through (reported).
// Every point becomes an isotropic Gaussian: 3DGS's nearest-neighbour scale (knn_scales.h),
// identity rotation, opacity 0.1, SH degree 0 with the DC term set to the colour.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/log/drive_log.h"

namespace streetsim {

struct InitOptions {
  FrameRange frames;
  double voxel_m = 0.15;
  double max_range_m = 60.0;
  bool drop_dynamic = false;
  bool sky = false;
  double sky_radius_m = 0;     // 0: twice max_range_m
  int sky_points = 200'000;    // on the whole sphere before culling
  int random_points = 100'000;  // camera-only logs without sparse points, where too few triangulate
  int min_triangulated_points = 1000;  // camera-only logs: fewer, and random points are used
  double random_min_depth_m = 2.0, random_max_depth_m = 50.0;
  float opacity = 0.1f;
  unsigned seed = 1;
};

struct InitStats {
  std::string source;  // "lidar", "colmap_points", "triangulated", "random_frusta"
  int frames_used = 0;
  size_t lidar_points_raw = 0;
  size_t voxels = 0;
  size_t seen = 0;  // points some camera coloured
  size_t sky_points = 0;
  size_t gaussians = 0;
  double median_scale_m = 0;
  double seconds = 0;
  std::vector<std::string> notes;
};

absl::StatusOr<GaussianStore> BuildInitialScene(const DriveLog& log, const InitOptions& options,
                                                InitStats* stats = nullptr);

// Points + linear RGB in [0,1] -> Gaussians (scales from nearest neighbours).
GaussianStore GaussiansFromPoints(const std::vector<Eigen::Vector3f>& points,
                                  const std::vector<Eigen::Vector3f>& rgb, float opacity,
                                  double* median_scale_m = nullptr);

}  // namespace streetsim
