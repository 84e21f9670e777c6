// Shared by the dynamic-scene server tests: a small field over a scene's Gaussians whose time
// planes and output heads are scaled so that Gaussians move by up to ~2 m and change colour over
// [start_us, end_us] (every time renders differently), an ego pose along x and the tests' front
// camera.
#pragma once

#include <cstdint>
#include <random>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "render/camera.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/train/dynamic_stage.h"

namespace streetsim::testing {

inline field::DeformationField MovingField(const GaussianStore& g, int64_t start_us, int64_t end_us) {
  field::FieldConfig c;
  c.channels = 4;
  c.base_resolution = 8;
  c.multires = {1, 2};
  c.time_resolution = 5;
  c.width = 16;
  absl::StatusOr<field::DeformationField> f =
      field::DeformationField::Create(c, train::AabbOfMeans(g.means), {start_us, end_us}, 11);
  EXPECT_TRUE(f.ok()) << f.status();
  const field::FieldLayout& L = f->layout();
  std::vector<float>& p = f->mutable_params();
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> u(-0.6f, 0.6f);
  for (const field::PlaneInfo& pi : L.planes) {
    if (!field::PlaneHasTime(pi.plane)) continue;
    for (size_t i = 0; i < pi.size(L.channels); ++i) p[pi.offset + i] += u(rng);
  }
  auto scale = [&](const field::DenseInfo& d, float s) {
    for (size_t i = 0; i < size_t(d.out) * d.in; ++i) p[d.w_offset + i] *= s;
    for (int i = 0; i < d.out; ++i) p[d.b_offset + i] *= s;
  };
  scale(L.pos2, 4.0f);
  scale(L.sh2, 3.0f);
  return std::move(*f);
}

inline Eigen::Isometry3d EgoAt(double x_m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation() = Eigen::Vector3d(x_m, 0.0, 0.0);
  return T;
}

// cam_front of the dynamic-scene tests' scene.json (128 x 64, f 80, 1.5 m ahead of the ego and
// 1.65 m up, looking along ego x) at ego x = x_m.
inline PinholeCamera FrontCamera(double x_m) {
  Eigen::Matrix4d T_ego_from_cam;
  T_ego_from_cam << 0, 0, 1, 1.5, -1, 0, 0, 0, 0, -1, 0, 1.65, 0, 0, 0, 1;
  PinholeCamera cam;
  cam.width = 128;
  cam.height = 64;
  cam.fx = cam.fy = 80;
  cam.cx = 63.5;
  cam.cy = 31.5;
  cam.T_world_from_cam = EgoAt(x_m) * Eigen::Isometry3d(T_ego_from_cam);
  return cam;
}

}  // namespace streetsim::testing
