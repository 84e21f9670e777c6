// LiDAR losses in training (scene/train/lidar_stage.h): the stage's gradients against finite
// differences of the LiDAR loss through the double-precision reference renderer; reflectance
// logits carried by densification, checkpoints and scene.ply; and a short training on the KITTI
// clip where the LiDAR loss must lower the held-out LiDAR range error.
#include "scene/train/lidar_stage.h"

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_backward.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "scene/eval/lidar_eval.h"
#include "scene/train/trainer.h"
#include "tests/lidar/lidar_test_scenes.h"
#include "tests/train/lidar_loss_reference.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;
const std::string kKitti = std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

std::string TempDir(const std::string& name) {
  const fs::path d = fs::path(STREETSIM_BINARY_DIR) / "test_tmp" / name;
  fs::remove_all(d);
  fs::create_directories(d);
  return d.string();
}

using lidar_test::SmallModel;

// n Gaussians 4..9 m in front of and behind a yawed sensor, within the beams' elevations.
GaussianStore RandomStore(std::mt19937& rng, int n, const Eigen::Isometry3d& T_world_from_lidar) {
  std::uniform_real_distribution<double> u(0, 1);
  GaussianStore g;
  g.sh_degree = 0;
  g.Resize(n);
  for (int i = 0; i < n; ++i) {
    const double r = 4 + 5 * u(rng);
    const double az = i % 5 == 0 ? M_PI + 0.3 * (u(rng) - 0.5) : 1.4 * (u(rng) - 0.5);
    const double el = (-20 + 20 * u(rng)) * M_PI / 180;
    const Eigen::Vector3d p = T_world_from_lidar * Eigen::Vector3d(r * std::cos(el) * std::cos(az),
                                                                  r * std::cos(el) * std::sin(az), r * std::sin(el));
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = static_cast<float>(p[k]);
      g.log_scales[i * 3 + k] = static_cast<float>(std::log(0.1 + 0.3 * u(rng)));
    }
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = static_cast<float>(u(rng) - 0.5 + (k == 0 ? 0.6 : 0.0));
    g.opacity_logits[i] = static_cast<float>(-1.0 + 2.5 * u(rng));
  }
  return g;
}


double ReferenceLoss(ThreadPool& pool, const GaussianStore& store, const std::vector<float>& logits,
                     const LidarFrameTarget& target, const LidarLossWeights& w) {
  const std::vector<float> refl = ReflectanceFromLogits(logits);
  LidarReferenceOutput ref;
  EXPECT_TRUE(RenderLidarReference(pool, store, target.model, target.sweep, &refl, &ref).ok());
  return DoubleLidarLoss(ref, target, w);
}

TEST(LidarTraining, StageGradientsMatchFiniteDifferencesOfTheReference) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(0, 1);
  ThreadPool pool(2);
  LidarFrameTarget target;
  target.model = SmallModel();
  Eigen::Isometry3d start = Eigen::Isometry3d::Identity();
  start.linear() = Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  start.translation() = Eigen::Vector3d(1.0, -0.5, 1.7);
  Eigen::Isometry3d end = start;
  end.translation() += Eigen::Vector3d(0.5, 0.1, 0.0);
  target.sweep = {start, end};
  const GaussianStore store = RandomStore(rng, 30, start);
  const size_t n = store.size();
  std::vector<float> logits(n);
  for (float& l : logits) l = static_cast<float>(2 * u(rng) - 1);

  // The "real" scan: the same scene 0.3 m off with other reflectances (returns where its alpha >=
  // 0.5), plus spurious returns on some rays the scene misses.
  GaussianStore moved = store;
  for (size_t i = 0; i < n; ++i) moved.means[i * 3] += 0.3f;
  std::vector<float> other(n);
  for (float& r : other) r = static_cast<float>(u(rng));
  LidarReferenceOutput real;
  ASSERT_TRUE(RenderLidarReference(pool, moved, target.model, target.sweep, &other, &real).ok());
  const size_t rays = real.alpha.size();
  target.range.assign(rays, 0.0f);
  target.intensity.assign(rays, 0.0f);
  for (size_t p = 0; p < rays; ++p) {
    if (real.alpha[p] >= 0.5) {
      target.range[p] = static_cast<float>(real.range_sum[p] / real.alpha[p]);
      target.intensity[p] = static_cast<float>(real.intensity_sum[p] / real.alpha[p]);
    } else if (u(rng) < 0.05) {
      target.range[p] = static_cast<float>(3 + 10 * u(rng));
      target.intensity[p] = static_cast<float>(u(rng));
    }
  }
  // Weights of the order the trainer uses, but comparable terms so that each one matters.
  LidarLossWeights w;
  w.range = 0.5f;
  w.ret = 0.3f;
  w.intensity = 0.4f;

  for (LidarRenderOptions::Kernel kernel : {LidarRenderOptions::Kernel::kScalar, LidarRenderOptions::Kernel::kSimd}) {
    SCOPED_TRACE(kernel == LidarRenderOptions::Kernel::kScalar ? "scalar" : "simd");
    LidarRenderer renderer(2);
    ASSERT_TRUE(renderer.Upload(store).ok());
    LidarGradOptions go;
    go.kernel = kernel;
    LidarGaussianGrads g;
    absl::StatusOr<LidarLossTerms> terms = LidarFrameLossAndGrads(renderer, logits, target, w, go, &g);
    ASSERT_TRUE(terms.ok()) << terms.status();
    EXPECT_GT(terms->range_l1_m, 0);
    EXPECT_GT(terms->return_bce, 0);
    EXPECT_GT(terms->intensity_l1, 0);
    EXPECT_NEAR(terms->total, ReferenceLoss(pool, store, logits, target, w), 1e-4 * terms->total);

    // Parameters: (group, index) for the Gaussians with the largest reflectance-logit and mean
    // gradients, one of each group per Gaussian.
    std::vector<size_t> order(n);
    for (size_t i = 0; i < n; ++i) order[i] = i;
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) {
      return std::fabs(g.reflectance[a]) + std::fabs(g.means[a * 3]) > std::fabs(g.reflectance[b]) + std::fabs(g.means[b * 3]);
    });
    int checked = 0, checked_refl = 0;
    double worst = 0;
    for (int k = 0; k < 5; ++k) {
      const size_t i = order[k];
      for (int group = 0; group < 5; ++group) {
        float an = 0;
        auto perturbed = [&](double h) {
          GaussianStore s = store;
          std::vector<float> l = logits;
          switch (group) {
            case 0: s.means[i * 3] += static_cast<float>(h); break;
            case 1: s.log_scales[i * 3 + 1] += static_cast<float>(h); break;
            case 2: s.rotations[i * 4 + 2] += static_cast<float>(h); break;
            case 3: s.opacity_logits[i] += static_cast<float>(h); break;
            default: l[i] += static_cast<float>(h); break;
          }
          return ReferenceLoss(pool, s, l, target, w);
        };
        switch (group) {
          case 0: an = g.means[i * 3]; break;
          case 1: an = g.log_scales[i * 3 + 1]; break;
          case 2: an = g.rotations[i * 4 + 2]; break;
          case 3: an = g.opacity_logits[i]; break;
          default: an = g.reflectance[i]; break;
        }
        const double h1 = 2e-4, h2 = 5e-5;
        const double fd1 = (perturbed(h1) - perturbed(-h1)) / (2 * h1);
        const double fd2 = (perturbed(h2) - perturbed(-h2)) / (2 * h2);
        // A step across a kink of the L1 or a tile / cull threshold: the two steps disagree.
        if (std::fabs(fd1 - fd2) > 0.01 * std::max(std::fabs(fd1), 1e-6)) continue;
        if (std::fabs(fd1) < 1e-5) continue;  // nothing measurable above the float rounding
        const double rel = std::fabs(an - fd1) / std::fabs(fd1);
        worst = std::max(worst, rel);
        EXPECT_LT(rel, 5e-3) << "group " << group << " gaussian " << i << " analytic " << an << " fd " << fd1;
        ++checked;
        checked_refl += group == 4;
      }
    }
    std::printf("checked %d parameters (%d reflectance logits), worst relative error %.2e\n", checked, checked_refl,
                worst);
    EXPECT_GE(checked, 12);
    EXPECT_GE(checked_refl, 2);
  }
}

// SH DC red tags each Gaussian (clones and split children copy SH): the reflectance logit must
// follow its Gaussian through clone, split and prune.
TEST(LidarTraining, DensificationKeepsReflectanceAligned) {
  std::mt19937 rng(3);
  GaussianStore init = RandomStore(rng, 40, Eigen::Isometry3d::Identity());
  for (size_t i = 0; i < init.size(); ++i) init.sh[i * 3] = static_cast<float>(i);
  TrainState st = TrainState::Init(init, 10.0, 1, 1);
  const size_t n = st.size();
  st.reflectance_logit.resize(n);
  st.reflectance_m.assign(n, 0.5f);
  st.reflectance_v.assign(n, 0.25f);
  for (size_t i = 0; i < n; ++i) st.reflectance_logit[i] = 0.1f * static_cast<float>(i) - 2.0f;
  Hyper h;
  for (size_t i = 0; i < n; ++i) {
    // Large view-space gradient on every other Gaussian: small ones clone, big ones split.
    st.grad_accum[i] = i % 2 == 0 ? 1.0f : 0.0f;
    st.denom[i] = 1;
    const float ls = i % 4 == 0 ? std::log(0.01f) : std::log(0.5f);
    for (int k = 0; k < 3; ++k) st.params.log_scales[i * 3 + k] = ls;
    if (i % 7 == 3) st.params.opacity_logits[i] = -10;  // pruned
  }
  size_t added = 0, removed = 0;
  DensifyAndPrune(&st, h, 1000, &added, &removed);
  EXPECT_GT(added, 0u);
  EXPECT_GT(removed, 0u);
  ASSERT_EQ(st.reflectance_logit.size(), st.size());
  ASSERT_EQ(st.reflectance_m.size(), st.size());
  ASSERT_EQ(st.reflectance_v.size(), st.size());
  size_t clones = 0, kept = 0;
  std::vector<int> seen(n, 0);
  for (size_t j = 0; j < st.size(); ++j) {
    const int tag = static_cast<int>(std::lround(st.params.sh[j * 48]));
    ASSERT_GE(tag, 0);
    ASSERT_LT(tag, static_cast<int>(n));
    EXPECT_EQ(st.reflectance_logit[j], 0.1f * static_cast<float>(tag) - 2.0f) << j;
    EXPECT_NE(tag % 7, 3) << "a pruned Gaussian survived";
    ++seen[tag];
    // Originals keep their moments, new Gaussians start at zero.
    if (st.reflectance_m[j] == 0.5f) ++kept;
    if (st.reflectance_m[j] == 0.0f) ++clones;
  }
  EXPECT_EQ(kept + clones, st.size());
  EXPECT_GT(clones, 0u);
  for (size_t i = 0; i < n; ++i) {
    if (i % 7 == 3) continue;
    // Clones (small, gradient): 2 copies; split parents (big, gradient): 2 children; others 1.
    EXPECT_EQ(seen[i], i % 2 == 0 ? 2 : 1) << i;
  }
}

TEST(LidarTraining, CheckpointCarriesReflectance) {
  std::mt19937 rng(5);
  const GaussianStore init = RandomStore(rng, 20, Eigen::Isometry3d::Identity());
  TrainState st = TrainState::Init(init, 10.0, 2, 1);
  const std::string dir = TempDir("lidar_training_ckpt");
  // Without reflectance (an older run, or --no-lidar-loss): loads with none.
  ASSERT_TRUE(SaveCheckpoint(st, dir + "/a.bin").ok());
  absl::StatusOr<TrainState> a = LoadCheckpoint(dir + "/a.bin");
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_TRUE(a->reflectance_logit.empty());
  const size_t n = st.size();
  for (size_t i = 0; i < n; ++i) {
    st.reflectance_logit.push_back(0.01f * i - 0.1f);
    st.reflectance_m.push_back(0.001f * i);
    st.reflectance_v.push_back(0.0001f * i);
  }
  st.reflectance_step = 17;
  ASSERT_TRUE(SaveCheckpoint(st, dir + "/b.bin").ok());
  absl::StatusOr<TrainState> b = LoadCheckpoint(dir + "/b.bin");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->reflectance_logit, st.reflectance_logit);
  EXPECT_EQ(b->reflectance_m, st.reflectance_m);
  EXPECT_EQ(b->reflectance_v, st.reflectance_v);
  EXPECT_EQ(b->reflectance_step, 17);
  EXPECT_EQ(b->params.means, st.params.means);
  // A truncated section and garbage after the curve are corrupt, not silently dropped.
  const auto size = fs::file_size(dir + "/b.bin");
  fs::copy_file(dir + "/b.bin", dir + "/c.bin");
  fs::resize_file(dir + "/c.bin", size - 5);
  EXPECT_EQ(LoadCheckpoint(dir + "/c.bin").status().code(), absl::StatusCode::kDataLoss);
  fs::copy_file(dir + "/a.bin", dir + "/d.bin");
  {
    std::FILE* f = std::fopen((dir + "/d.bin").c_str(), "ab");
    std::fputs("GARBAGE!", f);
    std::fclose(f);
  }
  EXPECT_EQ(LoadCheckpoint(dir + "/d.bin").status().code(), absl::StatusCode::kDataLoss);
  // A logit count that does not match the Gaussians is inconsistent.
  st.reflectance_logit.pop_back();
  st.reflectance_m.pop_back();
  st.reflectance_v.pop_back();
  ASSERT_TRUE(SaveCheckpoint(st, dir + "/e.bin").ok());
  EXPECT_EQ(LoadCheckpoint(dir + "/e.bin").status().code(), absl::StatusCode::kDataLoss);
  fs::remove_all(dir);
}

TEST(LidarTraining, ScenePlyCarriesReflectanceAndStillReads) {
  std::mt19937 rng(9);
  GaussianStore store = RandomStore(rng, 12, Eigen::Isometry3d::Identity());
  store.sh_degree = 0;
  std::vector<float> refl(store.size());
  for (size_t i = 0; i < refl.size(); ++i) refl[i] = static_cast<float>(i) / (refl.size() - 1);
  const std::string dir = TempDir("lidar_training_ply");
  ASSERT_TRUE(WriteGaussianPly(store, dir + "/scene.ply", &refl).ok());
  absl::StatusOr<GaussianStore> back = ReadGaussianPly(dir + "/scene.ply");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->means, store.means);
  EXPECT_EQ(back->opacity_logits, store.opacity_logits);
  EXPECT_EQ(back->rotations, store.rotations);
  absl::StatusOr<std::optional<std::vector<float>>> r = ReadPlyReflectance(dir + "/scene.ply", store.size());
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(r->has_value());
  EXPECT_EQ(**r, refl);
  std::vector<float> bad = refl;
  bad[3] = 1.5f;
  EXPECT_FALSE(WriteGaussianPly(store, dir + "/bad.ply", &bad).ok());
  bad.pop_back();
  EXPECT_FALSE(WriteGaussianPly(store, dir + "/bad.ply", &bad).ok());
  EXPECT_FALSE(fs::exists(dir + "/bad.ply"));
  fs::remove_all(dir);
}

// The stage on the KITTI clip: the gradient it adds is what it says (camera grads + LiDAR grads).
const DriveLog& Kitti() {
  static const DriveLog log = *OpenLog(kKitti);
  return log;
}

struct KittiRun {
  double median_m = -1, chamfer_m = -1, drop = -1;
};

KittiRun TrainAndMeasure(double lidar_weight, const std::string& name) {
  TrainOptions opt;
  opt.iterations = 150;
  opt.resolution_scale = 0.25;
  opt.init_voxel_m = 0.8;
  opt.checkpoint_every = 0;
  opt.write_outputs = false;
  opt.lidar_weight = lidar_weight;
  opt.lidar_columns = 512;
  opt.lidar_every = 1;
  opt.seed = 1;
  const std::string dir = TempDir(name);
  absl::StatusOr<TrainResult> r = Train(Kitti(), dir, opt);
  EXPECT_TRUE(r.ok()) << r.status();
  KittiRun run;
  if (!r.ok()) return run;
  absl::StatusOr<TrainState> st = LoadCheckpoint(dir + "/checkpoint.bin");
  EXPECT_TRUE(st.ok()) << st.status();
  if (!st.ok()) return run;
  EXPECT_EQ(st->reflectance_logit.empty(), lidar_weight == 0);
  std::vector<int> heldout;
  for (int f = 0; f < static_cast<int>(Kitti().frames.size()); ++f)
    if (IsHeldOut(f, opt.holdout_every) && f % 3 == 0) heldout.push_back(f);
  const std::vector<float> refl = ReflectanceFromLogits(st->reflectance_logit);
  LidarEvalOptions eo;
  eo.columns = 1024;
  absl::StatusOr<LidarEvalResult> ev =
      EvaluateLidar(Kitti(), heldout, st->params, refl.empty() ? nullptr : &refl, eo);
  EXPECT_TRUE(ev.ok()) << ev.status();
  if (!ev.ok()) return run;
  run.median_m = ev->mean.range_median_abs_m;
  run.chamfer_m = ev->mean.chamfer_m;
  run.drop = ev->mean.drop_accuracy;
  std::printf("lidar_weight %.1f: %zu held-out frames, range median %.3f m, chamfer %.3f m, drop acc %.3f\n",
              lidar_weight, ev->frames.size(), run.median_m, run.chamfer_m, run.drop);
  fs::remove_all(dir);
  return run;
}

TEST(LidarTraining, KittiLidarLossLowersHeldOutRangeError) {
  const KittiRun without = TrainAndMeasure(0.0, "lidar_training_without");
  const KittiRun with = TrainAndMeasure(1.0, "lidar_training_with");
  ASSERT_GT(without.median_m, 0);
  ASSERT_GT(with.median_m, 0);
  EXPECT_LT(with.median_m, without.median_m);
}

TEST(LidarTraining, StageAddsItsGradientsToTheCameraGradients) {
  LidarStageOptions lo;
  lo.columns = 256;
  absl::StatusOr<std::unique_ptr<LidarStage>> stage = LidarStage::Create(Kitti(), lo);
  ASSERT_TRUE(stage.ok()) << stage.status();
  std::mt19937 rng(11);
  // Gaussians around frame 0's LiDAR.
  const Eigen::Isometry3d T = Kitti().frames[0].T_world_from_ego * Kitti().lidars[0].T_ego_from_lidar;
  TrainState st = TrainState::Init(RandomStore(rng, 200, T), 10.0, 1, 1);
  GaussianGrads grads;
  grads.means.assign(st.size() * 3, 1.0f);
  grads.log_scales.assign(st.size() * 3, 2.0f);
  grads.rotations.assign(st.size() * 4, 3.0f);
  grads.opacity_logits.assign(st.size(), 4.0f);
  absl::StatusOr<double> loss = (*stage)->Step(&st, 0, 1, &grads);
  ASSERT_TRUE(loss.ok()) << loss.status();
  EXPECT_GT(*loss, 0);
  ASSERT_EQ(st.reflectance_logit.size(), st.size());
  EXPECT_EQ(st.reflectance_step, 1);
  // The same frame's gradients computed directly, at the logits before the Adam step (0).
  LidarRenderer renderer(0);
  ASSERT_TRUE(renderer.Upload(st.params).ok());
  absl::StatusOr<const LidarFrameTarget*> target = (*stage)->Target(0);
  ASSERT_TRUE(target.ok() && *target != nullptr);
  LidarGaussianGrads g;
  LidarGradOptions go;
  go.deterministic = true;
  ASSERT_TRUE(LidarFrameLossAndGrads(renderer, std::vector<float>(st.size(), 0.0f), **target, lo.weights, go, &g).ok());
  double norm = 0;
  for (size_t i = 0; i < st.size() * 3; ++i) {
    EXPECT_NEAR(grads.means[i] - 1.0f, g.means[i], 1e-4f * (1 + std::fabs(g.means[i])));
    norm += std::fabs(g.means[i]);
  }
  for (size_t i = 0; i < st.size(); ++i) {
    EXPECT_NEAR(grads.opacity_logits[i] - 4.0f, g.opacity_logits[i], 1e-4f * (1 + std::fabs(g.opacity_logits[i])));
  }
  EXPECT_GT(norm, 0);
  // Logits moved against their gradient.
  for (size_t i = 0; i < st.size(); ++i) {
    if (std::fabs(g.reflectance[i]) > 1e-8f) {
      EXPECT_LT(st.reflectance_logit[i] * g.reflectance[i], 0) << i;
    }
  }
  // Not due: nothing added.
  LidarStageOptions every2 = lo;
  every2.every = 2;
  absl::StatusOr<std::unique_ptr<LidarStage>> s2 = LidarStage::Create(Kitti(), every2);
  ASSERT_TRUE(s2.ok());
  const std::vector<float> before = grads.means;
  absl::StatusOr<double> skipped = (*s2)->Step(&st, 0, 3, &grads);
  ASSERT_TRUE(skipped.ok());
  EXPECT_EQ(*skipped, 0);
  EXPECT_EQ(grads.means, before);
  // Bad options.
  lo.columns = 4;
  EXPECT_FALSE(LidarStage::Create(Kitti(), lo).ok());
}

}  // namespace
}  // namespace streetsim::train
