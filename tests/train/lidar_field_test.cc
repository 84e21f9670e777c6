// LiDAR with the dynamic field (docs/training.md "LiDAR losses", "Dynamic field"): the fine
// stage's LiDAR step renders the deformed means and its gradient, summed with the camera's, is
// chained through the field by DeformBackward (the trainer's order) — checked against finite
// differences of the double reference loss of the deformed scene; and the LiDAR evaluation of a
// field scene (EvaluateLidar and `streetsim eval`) renders each frame deformed at the frame's time.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_backward.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/field_eval.h"
#include "scene/field/field_io.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/lidar_eval.h"
#include "scene/train/lidar_stage.h"
#include "scene/train/train_state.h"
#include "tests/field/field_test_util.h"
#include "tests/train/lidar_loss_reference.h"

namespace streetsim::train {
namespace {

const std::string kKitti = std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";
constexpr int kFrame = 3;

const DriveLog& Kitti() {
  static const DriveLog* log = [] {
    absl::StatusOr<DriveLog> l = OpenLog(kKitti);
    EXPECT_TRUE(l.ok()) << l.status();
    return new DriveLog(l.ok() ? std::move(*l) : DriveLog());
  }();
  return *log;
}

// n Gaussians 4..9 m in front of the LiDAR (within the beams' elevations), SH degree 3.
GaussianStore SceneInFront(int n, const Eigen::Isometry3d& T_world_from_lidar, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(0, 1);
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n);
  for (int i = 0; i < n; ++i) {
    const double r = 4 + 5 * u(rng), az = 1.2 * (u(rng) - 0.5), el = (-18 + 16 * u(rng)) * M_PI / 180;
    const Eigen::Vector3d p = T_world_from_lidar * Eigen::Vector3d(r * std::cos(el) * std::cos(az),
                                                                  r * std::cos(el) * std::sin(az), r * std::sin(el));
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = static_cast<float>(p[k]);
      g.log_scales[i * 3 + k] = static_cast<float>(std::log(0.15 + 0.3 * u(rng)));
    }
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = static_cast<float>(u(rng) - 0.5 + (k == 0 ? 0.6 : 0.0));
    g.opacity_logits[i] = static_cast<float>(-0.5 + 2.5 * u(rng));
  }
  return g;
}

// A small field over the scene whose every parameter is perturbed, so that Δx is a few
// centimetres to decimetres and depends on the sampling position and time.
field::DeformationField MovingField(const GaussianStore& scene, const DriveLog& log, double amplitude) {
  const field::FieldConfig c = field::testing::SmallConfig();
  absl::StatusOr<field::DeformationField> f = field::DeformationField::Create(
      c, AabbOfMeans(scene.means), {log.frames.front().time_us, log.frames.back().time_us}, 3);
  EXPECT_TRUE(f.ok()) << f.status();
  std::vector<float>& p = f->mutable_params();
  p = field::testing::RandomParams<float>(c, f->layout(), 5);
  std::mt19937 rng(11);
  std::uniform_real_distribution<float> u(-amplitude, amplitude);
  for (float& v : p) v += u(rng);
  return std::move(*f);
}


TEST(LidarField, FineStageGradientThroughTheFieldMatchesFiniteDifferences) {
  const DriveLog& log = Kitti();
  ASSERT_GT(log.frames.size(), static_cast<size_t>(kFrame));
  LidarStageOptions lo;
  lo.columns = 256;
  lo.deterministic = true;
  lo.num_threads = 2;
  lo.weights.range = 0.5f;  // comparable terms, so that each one matters
  lo.weights.ret = 0.3f;
  lo.weights.intensity = 0.4f;
  absl::StatusOr<std::unique_ptr<LidarStage>> stage = LidarStage::Create(log, lo);
  ASSERT_TRUE(stage.ok()) << stage.status();
  absl::StatusOr<const LidarFrameTarget*> target = (*stage)->Target(kFrame);
  ASSERT_TRUE(target.ok()) << target.status();
  ASSERT_NE(*target, nullptr);
  const LidarFrameTarget& tg = **target;

  const GaussianStore canonical = SceneInFront(24, tg.sweep.T_world_from_lidar_start, 7);
  const size_t n = canonical.size();
  TrainState st = TrainState::Init(canonical, 10.0, 1, 1);
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-1, 1);
  st.reflectance_logit.resize(n);
  for (float& l : st.reflectance_logit) l = u(rng);
  st.reflectance_m.assign(n, 0.0f);
  st.reflectance_v.assign(n, 0.0f);
  const std::vector<float> logits = st.reflectance_logit;  // Step takes an Adam step after its grads

  const field::DeformationField f = MovingField(canonical, log, 0.3f);
  const int64_t time_us = log.frames[kFrame].time_us;
  ThreadPool pool(2);
  field::FieldWorkspace ws;
  field::DeformedScene deformed;
  const field::CanonicalView cv{n, st.params.means.data(), st.params.sh.data()};
  ASSERT_TRUE(field::DeformScene(f, f.TimeCoordinate(time_us), cv, pool, ws, &deformed).ok());
  double max_dx = 0;
  for (float d : deformed.dx) max_dx = std::max(max_dx, static_cast<double>(std::fabs(d)));
  std::printf("max |dx| %.3f m\n", max_dx);
  ASSERT_GT(max_dx, 0.02) << "the field must move the Gaussians for the check to mean anything";

  // The camera's part: a linear loss w . (deformed means) standing in for RenderBackward.
  GaussianGrads grads;
  grads.means.resize(n * 3);
  grads.log_scales.assign(n * 3, 0.0f);
  grads.rotations.assign(n * 4, 0.0f);
  grads.opacity_logits.assign(n, 0.0f);
  grads.sh.assign(n * 3, 0.0f);  // active degree 0
  std::vector<float> w_cam(n * 3);
  for (float& v : w_cam) v = 0.05f * u(rng);
  grads.means = w_cam;

  // The trainer's order: LiDAR step on the deformed means, then the field's backward on the sum.
  absl::StatusOr<double> lidar_loss = (*stage)->Step(&st, kFrame, 1, &grads, &deformed.means);
  ASSERT_TRUE(lidar_loss.ok()) << lidar_loss.status();
  ASSERT_GT(*lidar_loss, 0);
  field::FieldHyper hyper;
  hyper.lambda_dx = 0;  // the Δ sparsity terms are field-only and checked in tests/field
  hyper.lambda_dsh = 0;
  std::vector<float> d_field;
  ASSERT_TRUE(field::DeformBackward(f, cv, deformed, 0, hyper, pool, ws, &grads, &d_field).ok());

  // A bad render_means size is an error, not a crash.
  GaussianGrads spare = grads;
  std::vector<float> short_means(3, 0.0f);
  EXPECT_FALSE((*stage)->Step(&st, kFrame, 1, &spare, &short_means).ok());

  const field::FieldQuery q = f.Query(time_us);
  std::vector<double> params0(f.params().begin(), f.params().end());
  std::vector<double> means0(canonical.means.begin(), canonical.means.end());
  const std::vector<float> refl = ReflectanceFromLogits(logits);
  auto loss = [&](const std::vector<double>& params, const std::vector<double>& means) {
    std::vector<double> dx(n * 3), dsh(n * 48);
    field::FieldWorkspace w2;
    field::FieldForward<double>(f.layout(), params.data(), q, means.data(), nullptr, n, dx.data(), dsh.data(), pool,
                                w2);
    GaussianStore s = canonical;
    double cam = 0;
    for (size_t i = 0; i < n * 3; ++i) {
      const double m = means[i] + dx[i];
      s.means[i] = static_cast<float>(m);
      cam += w_cam[i] * m;
    }
    LidarReferenceOutput ref;
    EXPECT_TRUE(RenderLidarReference(pool, s, tg.model, tg.sweep, &refl, &ref).ok());
    return cam + DoubleLidarLoss(ref, tg, lo.weights);
  };

  // Canonical means and field parameters with the largest analytic gradients.
  struct Param {
    bool field;
    size_t index;
    double analytic;
  };
  std::vector<Param> cands;
  for (size_t i = 0; i < n * 3; ++i) cands.push_back({false, i, grads.means[i]});
  std::vector<size_t> order(d_field.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::partial_sort(order.begin(), order.begin() + 40, order.end(),
                    [&](size_t a, size_t b) { return std::fabs(d_field[a]) > std::fabs(d_field[b]); });
  for (int k = 0; k < 40; ++k) cands.push_back({true, order[k], d_field[order[k]]});
  std::sort(cands.begin(), cands.end(), [](const Param& a, const Param& b) {
    return a.field != b.field ? a.field < b.field : std::fabs(a.analytic) > std::fabs(b.analytic);
  });

  int checked_means = 0, checked_field = 0;
  double worst = 0;
  for (const Param& p : cands) {
    int& checked = p.field ? checked_field : checked_means;
    if (checked >= 6) continue;
    auto perturbed = [&](double h) {
      std::vector<double> pa = params0, me = means0;
      (p.field ? pa : me)[p.index] += h;
      return loss(pa, me);
    };
    const double h1 = 2e-4, h2 = 5e-5;
    const double fd1 = (perturbed(h1) - perturbed(-h1)) / (2 * h1);
    const double fd2 = (perturbed(h2) - perturbed(-h2)) / (2 * h2);
    // A step across a kink of the L1 or a cull threshold: the two steps disagree.
    if (std::fabs(fd1 - fd2) > 0.01 * std::max(std::fabs(fd1), 1e-6)) continue;
    if (std::fabs(fd1) < 1e-5) continue;
    const double rel = std::fabs(p.analytic - fd1) / std::fabs(fd1);
    worst = std::max(worst, rel);
    EXPECT_LT(rel, 1e-2) << (p.field ? "field" : "mean") << " " << p.index << " analytic " << p.analytic << " fd "
                         << fd1;
    ++checked;
  }
  std::printf("checked %d canonical means, %d field parameters, worst relative error %.2e\n", checked_means,
              checked_field, worst);
  EXPECT_GE(checked_means, 4);
  EXPECT_GE(checked_field, 4);
}

TEST(LidarField, EvalRendersTheSceneDeformedAtTheFrameTime) {
  const DriveLog& log = Kitti();
  ASSERT_GT(log.frames.size(), static_cast<size_t>(kFrame));
  const Frame& frame = log.frames[kFrame];
  ASSERT_FALSE(frame.lidars.empty());
  const Eigen::Isometry3d T_world_from_lidar =
      frame.T_world_from_ego * log.lidars[frame.lidars[0].lidar].T_ego_from_lidar;
  const GaussianStore scene = SceneInFront(200, T_world_from_lidar, 9);
  auto field = std::make_shared<const field::DeformationField>(MovingField(scene, log, 0.3f));
  LidarEvalOptions opt;
  opt.columns = 512;
  const std::vector<int> frames = {kFrame};

  absl::StatusOr<LidarEvalResult> canonical = EvaluateLidar(log, frames, scene, nullptr, opt);
  ASSERT_TRUE(canonical.ok()) << canonical.status();
  EXPECT_FALSE(MakeStoreAtTime(nullptr, scene)) << "a static scene has no deformation";
  absl::StatusOr<LidarEvalResult> moved =
      EvaluateLidar(log, frames, scene, nullptr, opt, MakeStoreAtTime(field, scene));
  ASSERT_TRUE(moved.ok()) << moved.status();
  ASSERT_EQ(canonical->frames.size(), 1u);
  ASSERT_EQ(moved->frames.size(), 1u);
  std::printf("chamfer canonical %.4f m, deformed %.4f m\n", canonical->mean.chamfer_m, moved->mean.chamfer_m);
  EXPECT_GT(std::fabs(moved->mean.chamfer_m - canonical->mean.chamfer_m), 1e-3);

  // Exactly the scene deformed at the frame's time (not the canonical one, not another time).
  ThreadPool pool(2);
  absl::StatusOr<GaussianStore> at = DeformedStore(*field, scene, frame.time_us, pool);
  ASSERT_TRUE(at.ok()) << at.status();
  absl::StatusOr<LidarEvalResult> direct = EvaluateLidar(log, frames, *at, nullptr, opt);
  ASSERT_TRUE(direct.ok()) << direct.status();
  EXPECT_DOUBLE_EQ(moved->mean.chamfer_m, direct->mean.chamfer_m);
  EXPECT_DOUBLE_EQ(moved->mean.range_median_abs_m, direct->mean.range_median_abs_m);
  EXPECT_DOUBLE_EQ(moved->mean.drop_accuracy, direct->mean.drop_accuracy);

  // A reflectance of another length is an error.
  std::vector<float> refl(scene.size() + 1, 0.5f);
  EXPECT_FALSE(EvaluateLidar(log, frames, scene, &refl, opt, MakeStoreAtTime(field, scene)).ok());
}

std::string Slurp(const std::string& p) {
  std::ifstream f(p);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

// `streetsim eval` on a field scene: a short field training run's scene with a field that moves
// the Gaussians put in its place; the LiDAR metrics must change when field.bin is removed.
TEST(LidarField, EvalCommandDeformsAFieldScene) {
  const std::string bin = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
  const std::filesystem::path dir =
      std::filesystem::path(STREETSIM_BINARY_DIR) / "test_tmp" / ("lidar_field_eval." + std::to_string(getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  const std::string out = (dir / "out.json").string(), err = (dir / "err.txt").string();
  auto run = [&](const std::string& args) {
    const int status = std::system((bin + " " + cli_test::WithoutActorsUnlessNamed(args) + " >" + out + " 2>" + err).c_str());
    return WEXITSTATUS(status);
  };
  const std::string scene = (dir / "scene").string();
  ASSERT_EQ(run("train --log " + kKitti + " --out " + scene +
                " --iterations 2 --field s3gaussian --static-iterations 1 --field-size small --field-motion-prior 0"
                " --resolution-scale 0.12 --holdout-every 10 --voxel 0.8 --seed 3"),
            0)
      << Slurp(err);
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(scene + "/scene.ply");
  ASSERT_TRUE(store.ok()) << store.status();
  const std::string field_path = scene + "/" + field::kFieldFileName;
  ASSERT_TRUE(field::SaveField(MovingField(*store, Kitti(), 0.3f), field_path).ok());

  const std::string eval = "eval --scene " + scene + " --log " + kKitti + " --lidar-columns 512";
  ASSERT_EQ(run(eval), 0) << Slurp(err);
  const nlohmann::json deformed = nlohmann::json::parse(Slurp(out));
  std::filesystem::remove(field_path);
  ASSERT_EQ(run(eval), 0) << Slurp(err);
  const nlohmann::json canonical = nlohmann::json::parse(Slurp(out));
  const double a = deformed["mean"]["lidar_chamfer_m"], b = canonical["mean"]["lidar_chamfer_m"];
  std::printf("eval chamfer with field %.4f m, canonical %.4f m\n", a, b);
  EXPECT_GT(std::fabs(a - b), 1e-3);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace streetsim::train
