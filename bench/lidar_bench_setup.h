// The command line and scene shared by the LiDAR benches (lidar_bench, lidar_backward_bench):
//   [gaussians=500000] [columns=2048] [repeats=R] [simd|scalar|vulkan]
// on the synthetic street (SH degree 0), KITTI HDL-64E beams, the sensor 1.73 m up at x = 20 m.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <string>

#include <Eigen/Geometry>

#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim::bench {

struct LidarBenchSetup {
  int columns = 2048;
  int repeats = 0;
  std::string kernel = "simd";  // simd | scalar | vulkan
  LidarRenderOptions opt;       // the cpu kernel to use
  GaussianStore store;
  LidarModel model;
  Eigen::Isometry3d T_world_from_lidar = Eigen::Isometry3d::Identity();
};

// False (after printing why) for an unknown kernel.
inline bool ParseLidarBenchSetup(int argc, char** argv, int default_repeats, LidarBenchSetup* s) {
  SyntheticStreetOptions so;
  so.num_gaussians = argc > 1 ? std::strtoul(argv[1], nullptr, 10) : 500'000;
  so.sh_degree = 0;
  s->columns = argc > 2 ? std::atoi(argv[2]) : 2048;
  s->repeats = argc > 3 ? std::atoi(argv[3]) : default_repeats;
  s->kernel = argc > 4 ? argv[4] : "simd";
  if (s->kernel != "simd" && s->kernel != "scalar" && s->kernel != "vulkan") {
    std::fprintf(stderr, "kernel is simd, scalar or vulkan\n");
    return false;
  }
  s->opt.kernel = s->kernel == "simd" ? LidarRenderOptions::Kernel::kSimd : LidarRenderOptions::Kernel::kScalar;
  s->store = MakeSyntheticStreet(so);
  s->model = KittiHdl64e(s->columns);
  s->T_world_from_lidar.translation() = Eigen::Vector3d(20, 0, 1.73);
  return true;
}

}  // namespace streetsim::bench
