// Camera pose refinement (scene/train/pose_refinement.h): the pose gradient against finite
// differences of the double-precision forward, recovery of perturbed poses by gradient descent, the
// held-out interpolation, the corrections file and the checkpoint section.
#include "scene/train/pose_refinement.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>

#include "gtest/gtest.h"
#include "render/cpu/cpu_engine.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/train/losses.h"
#include "scene/train/train_state.h"
#include "tests/common/grad_check_scene.h"
#include "tests/common/params_view.h"
#include "tests/common/scratch_dir.h"

namespace streetsim::train {
namespace {

using gradcheck::LossDouble;
using gradcheck::RandomScene;

using streetsim::testing::StoreParamsView;

// Render of `s` from `cam` and the backward of the grad-check loss (sum of w . outputs).
GaussianGrads RenderAndBackward(Engine& engine, const gradcheck::Scene& s, const PinholeCamera& cam) {
  GaussianGrads grads;
  auto scene = engine.Upload(s.store);
  EXPECT_TRUE(scene.ok()) << scene.status();
  if (!scene.ok()) return grads;
  RenderOptions opt;
  opt.background = s.background;
  opt.keep_for_backward = true;
  RenderOutput out;
  EXPECT_TRUE(engine.Render(**scene, cam, opt, &out).ok());
  std::vector<float> g_rgb(s.w_rgb.begin(), s.w_rgb.end()), g_d(s.w_depth.begin(), s.w_depth.end()),
      g_a(s.w_alpha.begin(), s.w_alpha.end());
  EXPECT_TRUE(engine.RenderBackward(**scene, {g_rgb.data(), g_d.data(), g_a.data()}, {}, &grads).ok());
  return grads;
}

// The analytic pose gradient of the grad-check loss at `delta`.
PoseDelta AnalyticPoseGradient(const gradcheck::Scene& s, const PoseDelta& delta, ThreadPool& pool) {
  auto engine = CreateCpuEngine({.num_threads = 0, .precision = CpuPrecision::kDouble});
  const PinholeCamera cam = CorrectedCamera(s.cam, delta);
  return PoseGradient(StoreParamsView(s.store), RenderAndBackward(*engine, s, cam), cam, delta, pool);
}

struct PoseCase {
  int degree;
  bool at_nonzero_delta;
};

class PoseGradientCheck : public ::testing::TestWithParam<PoseCase> {
 protected:
  PoseDelta StartDelta() const {
    if (!GetParam().at_nonzero_delta) return PoseDelta{};
    return PoseDelta{0.004f, -0.006f, 0.003f, 0.03f, -0.02f, 0.05f};
  }
  // The camera at correction delta + x e_j.
  static PinholeCamera Camera(const gradcheck::Scene& s, PoseDelta delta, int j, double x) {
    delta[j] = static_cast<float>(delta[j] + x);
    return CorrectedCamera(s.cam, delta);
  }
};

// The camera moved by a correction sees what the unmoved camera sees of the scene moved by the
// inverse motion G = C(0) C(x)^-1: the same image. (SH degree 0: view-dependent colour does not
// move with the scene.)
TEST(PoseRefinement, MovingTheCameraRendersTheSceneMovedInverselyInPlace) {
  const gradcheck::Scene s = RandomScene(31, 24, 0);
  for (const PoseDelta delta : {PoseDelta{}, PoseDelta{0.004f, -0.006f, 0.003f, 0.03f, -0.02f, 0.05f}}) {
    auto engine = CreateCpuEngine({.num_threads = 0, .precision = CpuPrecision::kDouble});
    const PinholeCamera c0 = CorrectedCamera(s.cam, delta);
    const PoseDelta step = {0.01f, -0.02f, 0.015f, 0.05f, 0.03f, -0.04f};
    PoseDelta moved_delta = delta;
    for (int j = 0; j < 6; ++j) moved_delta[j] += step[j];
    const PinholeCamera c1 = CorrectedCamera(s.cam, moved_delta);
    const Eigen::Isometry3d G = c0.T_world_from_cam * c1.T_world_from_cam.inverse();
    GaussianStore moved = s.store;
    const Eigen::Quaterniond qG(G.linear());
    for (size_t i = 0; i < moved.size(); ++i) {
      Eigen::Map<Eigen::Vector3f> m(&moved.means[i * 3]);
      m = (G * m.cast<double>()).cast<float>();
      float* q = &moved.rotations[i * 4];
      const Eigen::Quaterniond qi(q[0], q[1], q[2], q[3]);
      const Eigen::Quaterniond r = qG * qi;
      q[0] = static_cast<float>(r.w()), q[1] = static_cast<float>(r.x()), q[2] = static_cast<float>(r.y()),
      q[3] = static_cast<float>(r.z());
    }
    RenderOptions ro;
    ro.background = s.background;
    RenderOutput a, b;
    auto sa = engine->Upload(s.store), sb = engine->Upload(moved);
    ASSERT_TRUE(sa.ok() && sb.ok());
    ASSERT_TRUE(engine->Render(**sa, c1, ro, &a).ok());
    ASSERT_TRUE(engine->Render(**sb, c0, ro, &b).ok());
    double max_diff = 0, changed = 0;
    RenderOutput unmoved;
    ASSERT_TRUE(engine->Render(**sa, c0, ro, &unmoved).ok());
    for (size_t k = 0; k < a.rgb.size(); ++k) {
      max_diff = std::max<double>(max_diff, std::abs(a.rgb[k] - b.rgb[k]));
      changed = std::max<double>(changed, std::abs(a.rgb[k] - unmoved.rgb[k]));
    }
    EXPECT_LT(max_diff, 1e-4);
    EXPECT_GT(changed, 0.05);  // the step is visible
  }
}

// PoseGradient is the chain rule through that motion: the engine's per-Gaussian gradients (held
// against finite differences in grad_check_test) times d(mean, rotation)/d(correction), the latter
// by central differences of G here, at a zero and a non-zero correction.
TEST_P(PoseGradientCheck, IsTheChainRuleThroughTheInverseSceneMotion) {
  const PoseCase c = GetParam();
  ThreadPool pool(0);
  const gradcheck::Scene s = RandomScene(31 + c.degree, 24, c.degree);
  const PoseDelta delta = StartDelta();
  const PinholeCamera c0 = Camera(s, delta, 0, 0);
  auto engine = CreateCpuEngine({.num_threads = 0, .precision = CpuPrecision::kDouble});
  const GaussianGrads grads = RenderAndBackward(*engine, s, c0);
  int visible = 0;
  for (float r : grads.radii) visible += r > 0;
  ASSERT_GE(visible, 18);
  const PoseDelta an = PoseGradient(StoreParamsView(s.store), grads, c0, delta, pool);

  for (int j = 0; j < 6; ++j) {
    const double h = 1e-4;
    double chain = 0;
    for (double sign : {1.0, -1.0}) {
      const Eigen::Isometry3d G = c0.T_world_from_cam * Camera(s, delta, j, sign * h).T_world_from_cam.inverse();
      const Eigen::Quaterniond qG(G.linear());
      for (size_t i = 0; i < s.store.size(); ++i) {
        const Eigen::Vector3d m = G * Eigen::Vector3f(&s.store.means[i * 3]).cast<double>();
        const float* q = &s.store.rotations[i * 4];
        const Eigen::Quaterniond r = qG * Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
        const double qn[4] = {r.w(), r.x(), r.y(), r.z()};
        for (int k = 0; k < 3; ++k) chain += sign * grads.means[i * 3 + k] * m[k] / (2 * h);
        for (int k = 0; k < 4; ++k) chain += sign * grads.rotations[i * 4 + k] * qn[k] / (2 * h);
      }
    }
    const double tolerance = 1e-4;
    EXPECT_NEAR(an[j], chain, tolerance * std::max(1.0, std::abs(chain)))
        << "parameter " << j << ": " << an[j] << " vs " << chain;
  }
}

// End to end against central differences of the double-precision forward. A camera motion moves
// every Gaussian across the 1/255 alpha cut and tile edges at once, so the loss is only piecewise
// smooth at small steps; at a step of 1e-3 the difference quotient is the slope to a few percent.
TEST_P(PoseGradientCheck, PointsAlongFiniteDifferencesOfTheRender) {
  const PoseCase c = GetParam();
  ThreadPool pool(0);
  const gradcheck::Scene s = RandomScene(31 + c.degree, 24, c.degree);
  const PoseDelta delta = StartDelta();
  const PoseDelta an = AnalyticPoseGradient(s, delta, pool);
  Eigen::Matrix<double, 6, 1> fd, a;
  for (int j = 0; j < 6; ++j) {
    auto L = [&](double x) {
      gradcheck::Scene moved = s;
      moved.cam = Camera(s, delta, j, x);
      return LossDouble(pool, moved, s.store);
    };
    fd[j] = (L(1e-3) - L(-1e-3)) / 2e-3;
    a[j] = an[j];
  }
  const double cosine = fd.dot(a) / (fd.norm() * a.norm());
  // Degree 3: the SH view direction's bias (PoseGradient); these random SH are strongly
  // view-dependent (measured: cosine 0.997-0.999, magnitude 0.87-0.88; degree 0: 0.993-0.999,
  // 0.97-1.07, the difference quotient's own spread).
  const bool sh = c.degree > 0;
  EXPECT_GT(cosine, sh ? 0.97 : 0.99) << "fd " << fd.transpose() << " / analytic " << a.transpose();
  EXPECT_NEAR(a.norm() / fd.norm(), 1.0, sh ? 0.2 : 0.1) << "fd " << fd.transpose() << " / analytic " << a.transpose();
}

INSTANTIATE_TEST_SUITE_P(Cases, PoseGradientCheck,
                         ::testing::Values(PoseCase{0, false}, PoseCase{0, true}, PoseCase{3, false},
                                           PoseCase{3, true}));

// Gradient descent on the correction alone brings a perturbed camera back to the pose the target
// image was rendered from.
TEST(PoseRefinement, RecoversAPerturbedPose) {
  ThreadPool pool(0);
  gradcheck::Scene s = RandomScene(5, 400, 0, 96, 72);
  auto engine = CreateCpuEngine({.num_threads = 0, .precision = CpuPrecision::kFloatSimd});
  auto scene = engine->Upload(s.store);
  ASSERT_TRUE(scene.ok());
  RenderOptions ro;
  ro.background = s.background;
  RenderOutput target;
  ASSERT_TRUE(engine->Render(**scene, s.cam, ro, &target).ok());
  // The log's pose is off by 0.6 degrees and 4 cm; the correction should undo it.
  const PoseDelta error = {0.006f, -0.008f, 0.004f, 0.03f, -0.025f, 0.02f};
  PinholeCamera logged = CorrectedCamera(s.cam, error);
  PoseDelta d{}, m{}, v{};
  auto residual = [&](const PoseDelta& corr) {
    const Eigen::Isometry3d diff = s.cam.T_world_from_cam.inverse() * CorrectedCamera(logged, corr).T_world_from_cam;
    return std::pair<double, double>{Eigen::AngleAxisd(diff.linear()).angle(), diff.translation().norm()};
  };
  const auto [rot0, trans0] = residual(d);
  ro.keep_for_backward = true;
  RenderOutput out;
  GaussianGrads grads;
  std::vector<float> d_rgb;
  for (int it = 1; it <= 300; ++it) {
    const PinholeCamera cam = CorrectedCamera(logged, d);
    ASSERT_TRUE(engine->Render(**scene, cam, ro, &out).ok());
    d_rgb.assign(out.rgb.size(), 0.0f);
    L1Loss(pool, out.rgb.data(), target.rgb.data(), out.rgb.size(), 1.0f, d_rgb.data());
    ASSERT_TRUE(engine->RenderBackward(**scene, {d_rgb.data(), nullptr, nullptr}, {}, &grads).ok());
    const PoseDelta g = PoseGradient(StoreParamsView(s.store), grads, cam, d, pool);
    AdamStepSmall(d.data(), g.data(), m.data(), v.data(), 3, 5e-4, it);
    AdamStepSmall(d.data() + 3, g.data() + 3, m.data() + 3, v.data() + 3, 3, 2e-3, it);
  }
  const auto [rot1, trans1] = residual(d);
  EXPECT_LT(rot1, rot0 / 5) << rot0 << " -> " << rot1 << " rad";
  EXPECT_LT(trans1, trans0 / 5) << trans0 << " -> " << trans1 << " m";
}

// Any backend's RenderBackward feeds the same pose gradient (the reduction runs on the host): the
// Vulkan engine (lavapipe in CI) against the cpu one, at a non-zero correction and SH degree 3.
TEST(PoseRefinement, VulkanAndCpuBackendsGiveOnePoseGradient) {
  absl::StatusOr<std::unique_ptr<Engine>> vk = CreateVulkanEngine(VulkanDevicePreference::kLavapipe);
  ASSERT_TRUE(vk.ok()) << vk.status();
  auto cpu = CreateCpuEngine({.num_threads = 0, .precision = CpuPrecision::kFloatSimd});
  ThreadPool pool(0);
  const gradcheck::Scene s = RandomScene(7, 200, 3, 96, 72);
  const PoseDelta delta = {0.004f, -0.006f, 0.003f, 0.03f, -0.02f, 0.05f};
  const PinholeCamera cam = CorrectedCamera(s.cam, delta);
  Eigen::Matrix<double, 6, 1> g[2];
  int k = 0;
  for (Engine* e : {cpu.get(), vk->get()}) {
    const PoseDelta p = PoseGradient(StoreParamsView(s.store), RenderAndBackward(*e, s, cam), cam, delta, pool);
    for (int j = 0; j < 6; ++j) g[k][j] = p[j];
    ++k;
  }
  EXPECT_GT(g[0].norm(), 1.0);
  EXPECT_LT((g[0] - g[1]).norm(), 1e-3 * g[0].norm()) << g[0].transpose() << " / " << g[1].transpose();
}

View ViewAt(int frame, int camera_obs, int64_t time_us) {
  View v;
  v.frame = frame;
  v.camera_obs = camera_obs;
  v.time_us = time_us;
  v.camera.width = 8;
  v.camera.height = 8;
  v.camera.fx = v.camera.fy = 8;
  return v;
}

PoseCorrection Correction(int frame, int camera_obs, int64_t time_us, float value) {
  PoseCorrection c;
  c.frame = frame;
  c.camera_obs = camera_obs;
  c.time_us = time_us;
  c.delta.fill(value);
  return c;
}

TEST(PoseRefinement, HeldOutViewsTakeTheirNeighboursCorrectionsInterpolated) {
  const std::vector<PoseCorrection> trained = {Correction(0, 0, 0, 0.0f), Correction(2, 0, 200, 0.02f),
                                               Correction(4, 0, 400, 0.04f), Correction(0, 1, 0, -0.01f)};
  const std::vector<View> views = {ViewAt(2, 0, 200),   // trained: its own
                                   ViewAt(3, 0, 350),   // between 2 and 4, 3/4 of the way
                                   ViewAt(5, 0, 500),   // after the last: the last's
                                   ViewAt(3, 1, 300),   // camera 1 has only frame 0
                                   ViewAt(3, 2, 300)};  // camera 2 has none: zero
  const std::vector<PoseDelta> d = CorrectionsForViews(trained, views);
  ASSERT_EQ(d.size(), views.size());
  EXPECT_FLOAT_EQ(d[0][4], 0.02f);
  EXPECT_NEAR(d[1][0], 0.035f, 1e-7);
  EXPECT_FLOAT_EQ(d[2][5], 0.04f);
  EXPECT_FLOAT_EQ(d[3][1], -0.01f);
  EXPECT_FLOAT_EQ(d[4][2], 0.0f);

  std::vector<View> moved = views;
  ApplyPoseCorrections(trained, &moved);
  EXPECT_TRUE(moved[4].camera.T_world_from_cam.isApprox(views[4].camera.T_world_from_cam));
  EXPECT_NEAR(moved[1].camera.T_world_from_cam.translation().x(), 0.035, 1e-6);
}

TEST(PoseRefinement, CorrectionsFileRoundTripsAndRejectsDamage) {
  const std::string dir = streetsim::testing::ScratchDir("pose_refinement", "corrections");
  EXPECT_TRUE(absl::IsNotFound(ReadPoseCorrections(dir).status()));
  std::vector<PoseCorrection> c = {Correction(0, 0, 0, 0.001f), Correction(4, 1, 400000, -0.002f)};
  c[1].delta[3] = 0.05f;
  ASSERT_TRUE(WritePoseCorrections(dir, c).ok());
  absl::StatusOr<std::vector<PoseCorrection>> back = ReadPoseCorrections(dir);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->size(), 2u);
  EXPECT_EQ((*back)[1].frame, 4);
  EXPECT_EQ((*back)[1].camera_obs, 1);
  EXPECT_EQ((*back)[1].time_us, 400000);
  EXPECT_EQ((*back)[1].delta, c[1].delta);

  const std::string path = (std::filesystem::path(dir) / kPoseCorrectionsFileName).string();
  for (const char* text : {"not json", "{\"corrections\": 3}",
                           "{\"corrections\": [{\"frame\": 1, \"camera_obs\": "
                           "0, \"time_us\": 0, \"rotation_rad\": [0, 0],"
                           " \"translation_m\": [0, 0, 0]}]}",
                           "{\"corrections\": [{\"frame\": 1, \"camera_obs\": "
                           "0, \"time_us\": 0, \"rotation_rad\": [2, 0, 0],"
                           " \"translation_m\": [0, 0, 0]}]}",
                           "{\"corrections\": [{\"frame\": 1, \"camera_obs\": "
                           "0, \"time_us\": 0, \"rotation_rad\": [0, 0, 0],"
                           " \"translation_m\": [0, 1e39, 0]}]}"}) {
    std::ofstream(path) << text;
    const absl::Status s = ReadPoseCorrections(dir).status();
    EXPECT_TRUE(absl::IsDataLoss(s)) << text << ": " << s;
    EXPECT_NE(s.message().find(kPoseCorrectionsFileName), std::string::npos) << s;
  }
}

TEST(PoseRefinement, CheckpointsCarryTheCorrectionsAndOlderOnesLoadWithout) {
  const std::string dir = streetsim::testing::ScratchDir("pose_refinement", "checkpoint");
  GaussianStore init;
  init.sh_degree = 0;
  init.Resize(3);
  for (float& q : init.rotations) q = 0.5f;
  TrainState st = TrainState::Init(init, 2.0, 4, 1);
  const std::string plain = dir + "/plain.bin", with_poses = dir + "/poses.bin";
  ASSERT_TRUE(SaveCheckpoint(st, plain).ok());
  st.reflectance_logit.assign(3, 0.5f);
  st.reflectance_m.assign(3, 0.0f);
  st.reflectance_v.assign(3, 0.0f);
  st.pose_delta.assign(24, 0.001f);
  st.pose_delta[7] = -0.25f;
  st.pose_m.assign(24, 0.0f);
  st.pose_v.assign(24, 1e-6f);
  st.pose_steps.assign(4, 17);
  ASSERT_TRUE(SaveCheckpoint(st, with_poses).ok());

  absl::StatusOr<TrainState> a = LoadCheckpoint(plain);
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_TRUE(a->pose_delta.empty());
  absl::StatusOr<TrainState> b = LoadCheckpoint(with_poses);
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->pose_delta, st.pose_delta);
  EXPECT_EQ(b->pose_v, st.pose_v);
  EXPECT_EQ(b->pose_steps, st.pose_steps);
  EXPECT_EQ(b->reflectance_logit.size(), 3u);

  // A run with another number of views refuses the checkpoint's corrections.
  EXPECT_TRUE(absl::IsFailedPrecondition(PreparePoseCorrections(5, &*b)));
  ASSERT_TRUE(PreparePoseCorrections(4, &*b).ok());
  EXPECT_EQ(b->pose_delta, st.pose_delta);  // kept
  ASSERT_TRUE(PreparePoseCorrections(7, &*a).ok());
  EXPECT_EQ(a->pose_delta.size(), 42u);
  EXPECT_EQ(a->pose_steps.size(), 7u);
  EXPECT_FLOAT_EQ(ViewCorrection(*b, 1)[1], -0.25f);

  // A non-finite correction is corruption, not a pose to render from.
  TrainState bad = st;
  bad.pose_delta[3] = std::nanf("");
  const std::string nan_path = dir + "/nan.bin";
  ASSERT_TRUE(SaveCheckpoint(bad, nan_path).ok());
  EXPECT_TRUE(absl::IsDataLoss(LoadCheckpoint(nan_path).status()));

  // A truncated pose section is corruption, not a checkpoint without poses.
  std::ifstream in(with_poses, std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::ofstream(with_poses, std::ios::binary | std::ios::trunc) << bytes.substr(0, bytes.size() - 20);
  EXPECT_TRUE(absl::IsDataLoss(LoadCheckpoint(with_poses).status()));
}

}  // namespace
}  // namespace streetsim::train
