// Scenes shared by the LiDAR tests (cpu and vulkan, forward and backward), so that the backends'
// tests run on the same inputs.
#pragma once

#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Geometry>

#include "render/lidar/lidar_gradients.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim::lidar_test {

// A Gaussian appended to a store (SH degree 0).
inline void AddGaussian(GaussianStore* s, const Eigen::Vector3d& mean, const Eigen::Vector3d& scale, float opacity,
                        const Eigen::Quaterniond& q = Eigen::Quaterniond::Identity()) {
  for (int k = 0; k < 3; ++k) {
    s->means.push_back(static_cast<float>(mean[k]));
    s->log_scales.push_back(static_cast<float>(std::log(scale[k])));
    s->sh.push_back(0.0f);
  }
  s->rotations.insert(s->rotations.end(), {static_cast<float>(q.w()), static_cast<float>(q.x()),
                                           static_cast<float>(q.y()), static_cast<float>(q.z())});
  s->opacity_logits.push_back(std::log(opacity / (1 - opacity)));
}

// A non-trivial sensor pose: 3 m along x, 1.7 m up, yawed 30 degrees, pitched 2.
inline Eigen::Isometry3d SensorPose() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translate(Eigen::Vector3d(3, -1, 1.7));
  T.rotate(Eigen::AngleAxisd(30 * M_PI / 180, Eigen::Vector3d::UnitZ()));
  T.rotate(Eigen::AngleAxisd(2 * M_PI / 180, Eigen::Vector3d::UnitY()));
  return T;
}

// A small sensor so that finite differences over every parameter stay cheap: 16 beams of the
// HDL-64E table (every 4th: non-uniform spacing), 256 columns.
inline LidarModel SmallModel() {
  const LidarModel full = KittiHdl64e();
  LidarModel m = full;
  m.beam_elevation_deg.clear();
  for (int b = 0; b < 64; b += 4) m.beam_elevation_deg.push_back(full.beam_elevation_deg[b]);
  m.columns = 256;
  return m;
}

// A gradient-check scene: Gaussians, reflectance, sensor, sweep and per-ray loss weights
// (the loss is the sum of w . outputs, so the weights are also the upstream gradients).
struct GradScene {
  GaussianStore store;
  std::vector<float> reflectance;
  LidarModel model;
  LidarSweepPose sweep;
  std::vector<double> w_range, w_alpha, w_intensity;
};

// n Gaussians 4..9 m around the sensor within the beams' elevations, a fifth of them straight
// behind it (on the seam), opacities below the 0.99 clamp, random reflectance and loss weights;
// `rolling`: the sensor moves 0.85 m and yaws 0.12 rad during the sweep.
inline GradScene RandomGradScene(unsigned seed, int n, bool rolling) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  GradScene s;
  s.model = SmallModel();
  Eigen::Isometry3d start = Eigen::Isometry3d::Identity();
  start.linear() = Eigen::AngleAxisd(0.2, Eigen::Vector3d(0.1, 0.05, 1).normalized()).toRotationMatrix();
  start.translation() = Eigen::Vector3d(1.0, -0.5, 1.7);
  Eigen::Isometry3d end = start;
  if (rolling) {
    end.translation() += Eigen::Vector3d(0.8, 0.3, 0.05);
    end.rotate(Eigen::AngleAxisd(0.12, Eigen::Vector3d::UnitZ()));
  }
  s.sweep = {start, end};
  GaussianStore& g = s.store;
  g.sh_degree = 0;
  g.Resize(n);
  for (int i = 0; i < n; ++i) {
    const double r = 4 + 5 * u(rng);
    const double az = i % 5 == 0 ? M_PI + 0.3 * (u(rng) - 0.5) : 1.4 * (u(rng) - 0.5);
    const double el = (-20 + 20 * u(rng)) * M_PI / 180;
    const Eigen::Vector3d p = start * Eigen::Vector3d(r * std::cos(el) * std::cos(az),
                                                      r * std::cos(el) * std::sin(az), r * std::sin(el));
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = static_cast<float>(p[k]);
      g.log_scales[i * 3 + k] = static_cast<float>(std::log(0.06 + 0.2 * u(rng)));
    }
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = static_cast<float>(u(rng) - 0.5 + (k == 0 ? 0.6 : 0.0));
    g.opacity_logits[i] = static_cast<float>(-1.5 + 2.5 * u(rng));
    g.sh[i * 3] = g.sh[i * 3 + 1] = g.sh[i * 3 + 2] = 0.0f;
    s.reflectance.push_back(static_cast<float>(0.1 + 0.8 * u(rng)));
  }
  const size_t P = static_cast<size_t>(s.model.beams()) * s.model.columns;
  for (size_t p = 0; p < P; ++p) {
    s.w_range.push_back(0.2 * (u(rng) - 0.5));
    s.w_alpha.push_back(u(rng) - 0.5);
    s.w_intensity.push_back(u(rng) - 0.3);
  }
  return s;
}

// A street for the backward comparisons (60k Gaussians of the procedural street: rays that
// saturate, the T < 1e-4 stop that the small gradient-check scenes avoid), a rolling sweep of the
// 1024-column HDL-64E, per-Gaussian reflectance and all three upstream gradients. Built once per
// process.
struct StreetBackwardCase {
  GaussianStore store;
  std::vector<float> refl;
  LidarModel model = KittiHdl64e(1024);
  LidarSweepPose sweep;
  std::vector<float> dr, da, di;
  LidarUpstreamGrads up() const { return {dr.data(), da.data(), di.data()}; }
};

inline const StreetBackwardCase& StreetBackward() {
  static const StreetBackwardCase* street = [] {
    auto* t = new StreetBackwardCase;
    SyntheticStreetOptions so;
    so.num_gaussians = 60'000;
    so.sh_degree = 0;
    t->store = MakeSyntheticStreet(so);
    t->refl.resize(t->store.size());
    for (size_t i = 0; i < t->refl.size(); ++i) t->refl[i] = static_cast<float>((i * 37) % 101) / 100.0f;
    t->sweep.T_world_from_lidar_start.translate(Eigen::Vector3d(20, 0.5, 1.73));
    t->sweep.T_world_from_lidar_end = t->sweep.T_world_from_lidar_start;
    t->sweep.T_world_from_lidar_end.translate(Eigen::Vector3d(1.5, 0, 0));
    t->sweep.T_world_from_lidar_end.rotate(Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()));
    const size_t P = static_cast<size_t>(t->model.beams()) * t->model.columns;
    std::mt19937 rng(4);
    std::uniform_real_distribution<float> u(-0.5f, 0.5f);
    for (size_t p = 0; p < P; ++p) {
      t->dr.push_back(0.1f * u(rng));
      t->da.push_back(u(rng));
      t->di.push_back(u(rng));
    }
    return t;
  }();
  return *street;
}

}  // namespace streetsim::lidar_test
