// Shared by the dynamic-scene server tests: a small field over a scene's Gaussians whose time
// planes and output heads are scaled so that Gaussians move by up to ~2 m and change colour over
// [start_us, end_us] (every time renders differently), and an ego pose along x.
#pragma once

#include <cstdint>
#include <random>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

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

}  // namespace streetsim::testing
