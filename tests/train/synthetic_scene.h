// Synthetic scenes and views for the trainer's convergence tests: a camera looking at the origin,
// and the moving-cluster scene (a static cloud plus a bright cluster that slides 1 m along x over a
// 2 s clip) rendered by the cpu engine into training / held-out views, each at its own time.
// Shared by tests/train/{convergence,dynamic_convergence}_test.cc and
// tests/field/ext_convergence_test.cc so that they train on the very same images.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/train/train_outputs.h"
#include "scene/train/trainer.h"

namespace streetsim::train::synthetic {

inline constexpr float kC0 = 0.28209479177387814f;

// OpenCV camera (x right, y down, z forward) at `eye` looking at the origin, world z up.
inline PinholeCamera LookAtOrigin(const Eigen::Vector3d& eye, int w, int h) {
  PinholeCamera c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = 0.9 * w;
  c.cx = (w - 1) / 2.0;
  c.cy = (h - 1) / 2.0;
  const Eigen::Vector3d z = (-eye).normalized();
  const Eigen::Vector3d x = z.cross(Eigen::Vector3d::UnitZ()).normalized();
  Eigen::Matrix3d R;
  R.col(0) = x;
  R.col(1) = z.cross(x);
  R.col(2) = z;
  c.T_world_from_cam = Eigen::Isometry3d::Identity();
  c.T_world_from_cam.linear() = R;
  c.T_world_from_cam.translation() = eye;
  return c;
}

// A rendered float RGB image as the 8-bit image a View carries (as the trainer writes previews).
using train::ToRgb8;

// The moving-cluster scene.
inline constexpr int kClusterSize = 40;
inline constexpr int64_t kClipUs = 2'000'000;

// Static cloud (first) and the cluster (last kClusterSize) at the clip's mid time.
inline GaussianStore SceneAtMidTime(uint64_t seed) {
  const auto logit = [](float a) { return std::log(a / (1 - a)); };
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  std::normal_distribution<float> nrm(0, 1);
  const int n_static = 200;
  GaussianStore g;
  g.sh_degree = 0;
  g.Resize(n_static + kClusterSize);
  for (int i = 0; i < n_static + kClusterSize; ++i) {
    const bool cluster = i >= n_static;
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = cluster ? 0.2f * nrm(rng) : 2 * u(rng) - 1;
      g.log_scales[i * 3 + k] = std::log(cluster ? 0.06f : 0.03f + 0.08f * u(rng));
    }
    g.rotations[i * 4] = 1;
    g.opacity_logits[i] = logit(cluster ? 0.9f : 0.5f + 0.4f * u(rng));
    for (int c = 0; c < 3; ++c) {
      const float colour = cluster ? (c == 0 ? 1.0f : 0.1f) : 0.3f * u(rng);
      g.sh[i * 3 + c] = (colour - 0.5f) / kC0;
    }
  }
  return g;
}

// The true scene at a time: the cluster's centre at x = -0.5 .. +0.5 m over the clip.
inline GaussianStore SceneAt(const GaussianStore& mid, int64_t time_us) {
  GaussianStore g = mid;
  const float dx = static_cast<float>(time_us) / kClipUs - 0.5f;
  for (size_t i = g.size() - kClusterSize; i < g.size(); ++i) g.means[i * 3] += dx;
  return g;
}

// Cameras half way round a band (so the cluster is seen from one side, like from a road), the
// i-th at time i / (n - 1) of the clip (phase shifts both angle and time).
inline std::vector<View> RenderMovingViews(const GaussianStore& mid, int n, double phase,
                                           const Eigen::Vector3f& background) {
  const int W = 96, H = 72;
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok()) << engine.status();
  std::vector<View> views;
  RenderOptions ro;
  ro.background = background;
  RenderOutput out;
  for (int i = 0; i < n; ++i) {
    const double s = (i + phase) / (n - 1);
    const int64_t t = std::llround(std::clamp(s, 0.0, 1.0) * kClipUs);
    const double az = -M_PI / 2 + M_PI * s, el = 0.25 + 0.1 * std::sin(3.0 * i);
    const PinholeCamera cam = LookAtOrigin(
        4.0 * Eigen::Vector3d(std::cos(az) * std::cos(el), std::sin(az) * std::cos(el), std::sin(el)), W, H);
    absl::StatusOr<std::unique_ptr<DeviceScene>> dev = (*engine)->Upload(SceneAt(mid, t));
    EXPECT_TRUE(dev.ok()) << dev.status();
    EXPECT_TRUE((*engine)->Render(**dev, cam, ro, &out).ok());
    View v;
    v.frame = i;
    v.time_us = t;
    v.name = "synthetic" + std::to_string(i);
    v.camera = cam;
    v.rgb8 = ToRgb8(out.rgb, W, H);
    views.push_back(std::move(v));
  }
  return views;
}

// The moving-cluster run: 24 training views, 6 held-out ones between them (phases 0.5 .. 5.5 of
// 23), and the start — the true Gaussians at the mid time, colours a little off.
struct MovingClusterRun {
  GaussianStore start;
  std::vector<View> train, test;
};

inline MovingClusterRun MovingClusterViews() {
  const Eigen::Vector3f background(0.25f, 0.4f, 0.6f);
  const GaussianStore mid = SceneAtMidTime(11);
  MovingClusterRun run;
  run.train = RenderMovingViews(mid, 24, 0.0, background);
  run.test = RenderMovingViews(mid, 6, 0.5, background);
  run.start = mid;
  std::mt19937_64 rng(2);
  std::normal_distribution<float> nrm(0, 0.05f / kC0);
  for (float& c : run.start.sh) c += nrm(rng);
  return run;
}

// The spec's hyper-parameters, but 500 iterations (100 static), deterministic, no depth loss or
// checkpoints, and a small field with test-scale learning rates (30x the spec's, which are tuned
// for 50 000 fine iterations). With `extended_modules` (ExtendedFieldConfig::WithModules), the
// extended field with those modules, its frame interval the training cameras' spacing in time.
inline TrainOptions MovingClusterOptions(FieldMode mode, const char* extended_modules = nullptr) {
  TrainOptions opt;
  opt.iterations = 500;
  opt.seed = 5;
  opt.checkpoint_every = 0;
  opt.depth_loss = false;
  opt.deterministic = true;
  opt.holdout_every = 0;
  opt.field.mode = mode;
  opt.field.static_iterations = 100;
  opt.field.config.channels = 8;
  opt.field.config.base_resolution = 16;
  opt.field.config.multires = {1, 2};
  opt.field.config.time_resolution = 8;
  opt.field.config.width = 32;
  opt.field.hyper.grid_lr_init *= 30;
  opt.field.hyper.grid_lr_final *= 30;
  opt.field.hyper.deformation_lr_init *= 30;
  opt.field.hyper.deformation_lr_final *= 30;
  if (extended_modules) {
    absl::StatusOr<field::ExtendedFieldConfig> ec = field::ExtendedFieldConfig::WithModules(extended_modules);
    EXPECT_TRUE(ec.ok()) << ec.status();
    if (ec.ok()) opt.field.extended = *ec;
    opt.field.frame_interval_us = kClipUs / 23;
  }
  return opt;
}

}  // namespace streetsim::train::synthetic
