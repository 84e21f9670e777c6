// The extended field's fine stage (--field extended) on the moving-cluster scene of
// tests/train/dynamic_convergence_test.cc (its scene and cameras, repeated here): with every
// module on it must train like S3Gaussian's field — held-out PSNR clearly above the static model —
// measured through the scene directory (field.bin + field_ext.bin, LoadSceneField), i.e. with the
// extension at inference.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>
#include <unistd.h>

#include <Eigen/Geometry>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/trainer.h"

namespace streetsim::train {
namespace {

constexpr float kC0 = 0.28209479177387814f;
constexpr int kClusterSize = 40;
constexpr int64_t kClipUs = 2'000'000;

float Logit(float a) { return std::log(a / (1 - a)); }

// Static cloud (first) and the cluster (last kClusterSize) at the clip's mid time.
GaussianStore SceneAtMidTime(uint64_t seed) {
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
    g.opacity_logits[i] = Logit(cluster ? 0.9f : 0.5f + 0.4f * u(rng));
    for (int c = 0; c < 3; ++c) {
      const float colour = cluster ? (c == 0 ? 1.0f : 0.1f) : 0.3f * u(rng);
      g.sh[i * 3 + c] = (colour - 0.5f) / kC0;
    }
  }
  return g;
}

// The true scene at a time: the cluster's centre at x = -0.5 .. +0.5 m over the clip.
GaussianStore SceneAt(const GaussianStore& mid, int64_t time_us) {
  GaussianStore g = mid;
  const float dx = static_cast<float>(time_us) / kClipUs - 0.5f;
  for (size_t i = g.size() - kClusterSize; i < g.size(); ++i) g.means[i * 3] += dx;
  return g;
}

PinholeCamera LookAtOrigin(const Eigen::Vector3d& eye, int w, int h) {
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

// Cameras half way round a band (so the cluster is seen from one side, like from a road), the
// i-th at time i / (n - 1) of the clip (phase shifts both angle and time).
std::vector<View> RenderViews(const GaussianStore& mid, int n, double phase, const Eigen::Vector3f& background) {
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
    v.rgb8 = cv::Mat(H, W, CV_8UC3);
    for (int y = 0; y < H; ++y)
      for (int x = 0; x < W * 3; ++x)
        v.rgb8.ptr<uint8_t>(y)[x] =
            static_cast<uint8_t>(std::lround(std::clamp(out.rgb[static_cast<size_t>(y) * W * 3 + x], 0.0f, 1.0f) * 255));
    views.push_back(std::move(v));
  }
  return views;
}

struct RunResult {
  double heldout_dir = 0;      // EvaluateSceneDir: the scene directory as eval reads it
  double heldout_trainer = 0;  // TrainResult::heldout
  double train = 0;            // training PSNR, mean of the last 50 iterations
};

RunResult HeldOut(FieldMode mode, const char* modules, const std::string& name) {
  const Eigen::Vector3f background(0.25f, 0.4f, 0.6f);
  const GaussianStore mid = SceneAtMidTime(11);
  const std::vector<View> train = RenderViews(mid, 24, 0.0, background);
  const std::vector<View> test = RenderViews(mid, 6, 0.5, background);
  GaussianStore start = mid;
  std::mt19937_64 rng(2);
  std::normal_distribution<float> nrm(0, 0.05f / kC0);
  for (float& c : start.sh) c += nrm(rng);
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
  if (modules) {
    absl::StatusOr<field::ExtendedFieldConfig> ec = field::ExtendedFieldConfig::WithModules(modules);
    EXPECT_TRUE(ec.ok());
    opt.field.extended = *ec;
    opt.field.frame_interval_us = kClipUs / 23;  // the training cameras' spacing in time
  }
  const auto dir = std::filesystem::temp_directory_path() /
                   ("streetsim_ext_convergence_" + std::to_string(getpid()) + "_" + name);
  std::filesystem::remove_all(dir);
  RunResult run;
  absl::StatusOr<TrainResult> r = TrainOnViews(train, &start, test, dir.string(), opt);
  EXPECT_TRUE(r.ok()) << r.status();
  if (!r.ok()) return run;
  EXPECT_EQ(std::filesystem::exists(dir / field::kExtendedFieldFileName), modules != nullptr);
  run.heldout_trainer = r->heldout.mean.psnr;
  run.train = r->train_psnr_mean50;
  absl::StatusOr<GaussianStore> scene = ReadGaussianPly((dir / "scene.ply").string());
  EXPECT_TRUE(scene.ok()) << scene.status();
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok());
  if (scene.ok() && engine.ok()) {
    absl::StatusOr<SceneMeta> meta = ReadSceneMeta(dir.string());
    EXPECT_TRUE(meta.ok());
    const Eigen::Vector3f bg(meta->background[0], meta->background[1], meta->background[2]);
    absl::StatusOr<EvalResult> ev = EvaluateSceneDir(**engine, dir.string(), *scene, test, bg);
    EXPECT_TRUE(ev.ok()) << ev.status();
    if (ev.ok()) run.heldout_dir = ev->mean.psnr;
  }
  std::filesystem::remove_all(dir);
  std::fprintf(stderr, "%s: training PSNR (last 50) %.2f dB, held-out %.2f dB (scene directory), %.2f dB (trainer)\n",
               name.c_str(), r->train_psnr_mean50, run.heldout_dir, run.heldout_trainer);
  return run;
}

TEST(ExtendedConvergence, EveryModuleTrainsLikeTheField) {
  const RunResult st = HeldOut(FieldMode::kStatic, nullptr, "static");
  const RunResult ext = HeldOut(FieldMode::kS3Gaussian, "all", "extended_all");
  // The fine stage is chaotic to the last bit (S3Gaussian's own held-out PSNR ranges 36.7-40.4 dB
  // over runs of this scene; the static model 33.0): margins below that spread. Before the gate
  // (extended_config.h) every module on reached 33.2 dB held-out.
  EXPECT_GT(ext.train, st.train + 3.0);
  EXPECT_GT(ext.heldout_dir, st.heldout_dir + 1.5);
}

}  // namespace
}  // namespace streetsim::train
