// Procedural street-like Gaussian scenes for benchmarks and tests when a trained scene of a given
// size is needed: road surface, facades on both sides, parked cars, poles and trees, clutter and a
// far sky shell, with Gaussians behind the camera too (as in any scene of a whole log).
#pragma once

#include <cstdint>

#include <Eigen/Geometry>

#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

struct SyntheticStreetOptions {
  size_t num_gaussians = 100'000;
  uint64_t seed = 1;
  int sh_degree = 3;
  double street_length_m = 160;  // along +x, starting 30 m behind the origin
  double street_half_width_m = 7;
};

// World frame: x along the street, y left, z up; road at z = 0.
GaussianStore MakeSyntheticStreet(const SyntheticStreetOptions& options);

// A KITTI-like forward camera (1242x375, fx = fy = 721.5) at `x_m` along the street, 1.65 m up,
// looking down the street (T_world_from_cam in the OpenCV camera convention).
Eigen::Isometry3d StreetCameraPose(double x_m, double lateral_m = 0.0);

}  // namespace streetsim
