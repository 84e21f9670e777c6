// The trainer on images of a known scene, isolated from data problems (poses, exposure, LiDAR):
// a few hundred random Gaussians rendered by the cpu engine from cameras around them become the
// training views; training starts from fewer, grey, perturbed Gaussians and must fit the views
// (a correct 3DGS reaches well over 30 dB on such a scene within a few hundred iterations), and
// views between the training cameras must come out nearly as well.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>

#include <Eigen/Geometry>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/train/trainer.h"
#include "tests/train/synthetic_scene.h"

namespace streetsim::train {
namespace {

using synthetic::kC0;
using synthetic::LookAtOrigin;
using synthetic::ToRgb8;

// A random scene in [-1, 1]^3: anisotropic, rotated, mostly opaque, coloured Gaussians (SH degree
// 0: the trainer's SH schedule only reaches degree 1 at iteration 1000).
GaussianStore RandomScene(int n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  std::normal_distribution<float> nrm(0, 1);
  GaussianStore g;
  g.sh_degree = 0;
  g.Resize(n);
  for (int i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) g.means[i * 3 + k] = 2 * u(rng) - 1;
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = std::log(0.03f + 0.12f * u(rng));
    Eigen::Vector4f q(nrm(rng), nrm(rng), nrm(rng), nrm(rng));
    q.normalize();
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = q[k];
    const float a = 0.5f + 0.45f * u(rng);
    g.opacity_logits[i] = std::log(a / (1 - a));
    for (int c = 0; c < 3; ++c) g.sh[i * 3 + c] = (u(rng) - 0.5f) / kC0;
  }
  return g;
}

// Cameras on a band around the scene: azimuth evenly spaced (offset by `phase` of a step),
// elevation alternating.
std::vector<PinholeCamera> Ring(int n, double phase, int w, int h) {
  std::vector<PinholeCamera> cams;
  for (int i = 0; i < n; ++i) {
    const double az = 2 * M_PI * (i + phase) / n, el = (i % 2 ? 0.35 : -0.1) + 0.1 * std::sin(3.0 * i);
    const double r = 4.0;
    cams.push_back(LookAtOrigin(r * Eigen::Vector3d(std::cos(az) * std::cos(el), std::sin(az) * std::cos(el),
                                                    std::sin(el)),
                                w, h));
  }
  return cams;
}

std::vector<View> RenderViews(const GaussianStore& scene, const std::vector<PinholeCamera>& cams,
                              const Eigen::Vector3f& background) {
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok()) << engine.status();
  absl::StatusOr<std::unique_ptr<DeviceScene>> dev = (*engine)->Upload(scene);
  EXPECT_TRUE(dev.ok()) << dev.status();
  RenderOptions ro;
  ro.background = background;
  RenderOutput out;
  std::vector<View> views;
  for (size_t i = 0; i < cams.size(); ++i) {
    EXPECT_TRUE((*engine)->Render(**dev, cams[i], ro, &out).ok());
    View v;
    v.frame = static_cast<int>(i);
    v.name = "synthetic" + std::to_string(i);
    v.camera = cams[i];
    v.rgb8 = ToRgb8(out.rgb, cams[i].width, cams[i].height);
    views.push_back(std::move(v));
  }
  return views;
}

// 3DGS-like start: a subset of the true centres, moved by N(0, sigma), grey, opacity 0.1,
// isotropic scale from the mean distance to the 3 nearest starting points, identity rotation.
GaussianStore PerturbedStart(const GaussianStore& truth, int n, float sigma, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> nrm(0, sigma);
  GaussianStore g;
  g.sh_degree = 0;
  g.Resize(n);
  for (int i = 0; i < n; ++i) {
    const int j = i * static_cast<int>(truth.size()) / n;
    for (int k = 0; k < 3; ++k) g.means[i * 3 + k] = truth.means[j * 3 + k] + nrm(rng);
    g.rotations[i * 4] = 1;
    for (int k = 1; k < 4; ++k) g.rotations[i * 4 + k] = 0;
    g.opacity_logits[i] = std::log(0.1f / 0.9f);
    for (int c = 0; c < 3; ++c) g.sh[i * 3 + c] = 0;
  }
  for (int i = 0; i < n; ++i) {
    float best[3] = {1e9f, 1e9f, 1e9f};
    for (int j = 0; j < n; ++j) {
      if (j == i) continue;
      float d2 = 0;
      for (int k = 0; k < 3; ++k) d2 += std::pow(g.means[i * 3 + k] - g.means[j * 3 + k], 2.0f);
      for (int b = 0; b < 3; ++b)
        if (d2 < best[b]) std::swap(d2, best[b]);
    }
    const float s = std::sqrt(std::max(1e-7f, (best[0] + best[1] + best[2]) / 3));
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = std::log(s);
  }
  return g;
}

// Noisy colours (sigma in [0, 1] colour units) taken from the true Gaussian each start point came from.
void NoisyColours(const GaussianStore& truth, float sigma, uint64_t seed, GaussianStore* start) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> nrm(0, sigma / kC0);
  const int Ks = start->sh_coeffs(), Kt = truth.sh_coeffs();
  for (size_t i = 0; i < start->size(); ++i) {
    const size_t j = i * truth.size() / start->size();
    for (int c = 0; c < 3; ++c) start->sh[i * Ks * 3 + c] = truth.sh[j * Kt * 3 + c] + nrm(rng);
  }
}

struct Fit {
  double train_psnr = 0, heldout_psnr = 0, heldout_ssim = 0;
  size_t gaussians = 0;
};

Fit TrainOn(const GaussianStore& start, int iterations, const std::string& name) {
  const int W = 96, H = 72;
  const Eigen::Vector3f background(0.25f, 0.4f, 0.6f);
  const GaussianStore truth = RandomScene(300, 11);
  const std::vector<View> train = RenderViews(truth, Ring(24, 0.0, W, H), background);
  // Held-out cameras between the training ones (half an azimuth step, other elevations).
  const std::vector<View> test = RenderViews(truth, Ring(6, 0.125, W, H), background);
  TrainOptions opt;  // the spec's hyper-parameters
  opt.iterations = iterations;
  opt.seed = 5;
  opt.checkpoint_every = 0;
  opt.depth_loss = false;
  opt.deterministic = true;
  opt.holdout_every = 0;
  const auto dir = std::filesystem::temp_directory_path() / ("streetsim_convergence_test_" + name);
  std::filesystem::remove_all(dir);
  absl::StatusOr<TrainResult> r = TrainOnViews(train, &start, test, dir.string(), opt, [](const Progress& p) {
    if (p.iteration % 100 == 0)
      std::fprintf(stderr, "it %4lld  loss %.4f  psnr %.2f  %zu Gaussians\n", static_cast<long long>(p.iteration),
                   p.loss, p.psnr, p.gaussians);
  });
  EXPECT_TRUE(r.ok()) << r.status();
  std::filesystem::remove_all(dir);
  if (!r.ok()) return {};
  std::fprintf(stderr, "%s: %d iterations: training PSNR (last 50) %.2f dB, held-out %.2f dB / SSIM %.4f, %zu Gaussians\n",
               name.c_str(), iterations, r->train_psnr_mean50, r->heldout.mean.psnr, r->heldout.mean.ssim,
               r->gaussians);
  return {r->train_psnr_mean50, r->heldout.mean.psnr, r->heldout.mean.ssim, r->gaussians};
}

// Near the solution (true Gaussians, centres moved by 3 cm, colours off by 0.05): the loop must
// settle on it and stay there (no densification before 500).
TEST(TrainerConvergence, SettlesOnTheTrueSceneFromNearby) {
  const GaussianStore truth = RandomScene(300, 11);
  GaussianStore start = truth;
  std::mt19937_64 rng(1);
  std::normal_distribution<float> nrm(0, 0.03f);
  for (float& x : start.means) x += nrm(rng);
  NoisyColours(truth, 0.05f, 2, &start);
  const Fit f = TrainOn(start, 400, "nearby");
  EXPECT_GT(f.train_psnr, 40.0);
  EXPECT_GT(f.heldout_psnr, 40.0);
}

// A 3DGS-like start: every true centre moved by 5 cm, colours off by 0.1 (as from coloured LiDAR
// points), opacity 0.1, isotropic k-NN scales, identity rotations. Measured: 24.96 / 27.69 /
// 30.62 / 32.06 dB training PSNR after 200 / 400 / 600 / 800 iterations (the log-scale learning
// rate 5e-3 is what limits it: the k-NN start is 2-5x the true scales).
TEST(TrainerConvergence, FitsRenderedViewsOfAKnownScene) {
  const GaussianStore truth = RandomScene(300, 11);
  GaussianStore start = PerturbedStart(truth, 300, 0.05f, 3);
  NoisyColours(truth, 0.1f, 2, &start);
  const Fit f = TrainOn(start, 800, "perturbed");
  EXPECT_GT(f.train_psnr, 30.5);
  EXPECT_GT(f.heldout_psnr, 30.0);
  EXPECT_GT(f.heldout_ssim, 0.95);
  EXPECT_GT(f.gaussians, 300u);  // densification ran (from 500, every 100)
}

}  // namespace
}  // namespace streetsim::train
