// A small scene whose deformation field moves a band of Gaussians and leaves the rest still, a
// camera looking down on it and a cpu engine: shared by the tests of what is rendered from a
// field scene (eval outputs, the served scene).
#pragma once

#include <cmath>
#include <memory>
#include <random>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/gaussian_store.h"
#include "tests/field/field_test_util.h"

namespace streetsim::train::testing {

inline constexpr float kC0 = 0.28209479177387814f;

// The field of tests/field/static_skip_test.cc: the finest xt plane varies in time only over its
// middle texel columns, so Gaussians near x = 1 (the AABB's centre) move and the others do not.
inline field::DeformationField BandField() {
  absl::StatusOr<field::DeformationField> f =
      field::DeformationField::Create(field::testing::SmallConfig(), field::testing::TestAabb(), {0, 2'000'000}, 7);
  EXPECT_TRUE(f.ok());
  field::testing::AddTimeVaryingBand(&*f, 1);
  return std::move(*f);
}

// SH degree 3 Gaussians: `n_band` at x in [0.8, 1.2] (inside the band), the rest near the AABB's
// x ends, all spread over y and near z = 0.
inline GaussianStore BandScene(int n_band, int n_far) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> u(0, 1);
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n_band + n_far);
  for (int i = 0; i < n_band + n_far; ++i) {
    const bool band = i < n_band;
    g.means[i * 3] = band ? 0.8f + 0.4f * u(rng) : (i % 2 ? -2.9f + 0.6f * u(rng) : 4.3f + 0.6f * u(rng));
    g.means[i * 3 + 1] = -1.5f + 5.0f * u(rng);
    g.means[i * 3 + 2] = 0.2f * u(rng);
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = std::log(0.05f + 0.05f * u(rng));
    g.rotations[i * 4] = 1;
    g.opacity_logits[i] = 1.5f;
    for (int c = 0; c < 3; ++c) g.sh[i * 48 + c] = (0.3f + 0.6f * u(rng) - 0.5f) / kC0;
  }
  return g;
}

// Looking straight down at the scene from 12 m above x = 1, y = 1.
inline PinholeCamera TopCamera() {
  PinholeCamera c;
  c.width = 96;
  c.height = 72;
  c.fx = c.fy = 86;
  c.cx = 47.5;
  c.cy = 35.5;
  c.T_world_from_cam = Eigen::Isometry3d::Identity();
  Eigen::Matrix3d R;
  R << 1, 0, 0, 0, -1, 0, 0, 0, -1;
  c.T_world_from_cam.linear() = R;
  c.T_world_from_cam.translation() = Eigen::Vector3d(1, 1, 12);
  return c;
}

inline std::unique_ptr<Engine> CpuEngine() {
  absl::StatusOr<std::unique_ptr<Engine>> e = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(e.ok()) << e.status();
  return std::move(*e);
}

}  // namespace streetsim::train::testing
