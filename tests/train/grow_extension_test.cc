// Growing the extended field's modules on an S3Gaussian run's fine-stage checkpoint
// (FieldOptions::grow_extension, docs/training.md "Growing modules on a trained field"): the grown
// field deforms the Gaussians as the checkpoint's field did, its Adam counts from the iteration it
// joined at, and the resume checks that make a lost or mismatched extension an error.
#include <cmath>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/train_state.h"
#include "tests/common/scratch_dir.h"
#include "tests/train/field_stage_fixtures.h"

namespace streetsim::train {
namespace {

TrainState RandomState(size_t n, uint64_t seed) {
  return TrainState::Init(fixtures::ScatteredGaussians(n, seed), 10.0, 1, 1);
}

// One fine iteration's field step with made-up upstream gradients (the renderer's stand-in).
void Step(DynamicStage& stage, const TrainState& st, int64_t fine_iteration, int64_t time_us, ThreadPool& pool) {
  ASSERT_TRUE(stage.Deform(st, 3, time_us, pool).ok());
  const size_t n = st.size();
  std::mt19937_64 rng(fine_iteration);
  std::normal_distribution<float> g(0, 1e-3f);
  GaussianGrads grads;
  for (auto [v, k] : {std::pair{&grads.means, 3},
                      {&grads.log_scales, 3},
                      {&grads.rotations, 4},
                      {&grads.opacity_logits, 1},
                      {&grads.sh, 48}}) {
    v->resize(n * k);
    for (float& x : *v) x = g(rng);
  }
  absl::StatusOr<double> loss = stage.Backward(st, 3, fine_iteration, &grads, pool);
  ASSERT_TRUE(loss.ok()) << loss.status();
}

// Each test grows modules on an S3Gaussian run's checkpoint: `st` after `steps` fine iterations
// (view times dt_us apart), saved in `dir` at fine iteration `steps`.
class GrowExtension : public ::testing::Test {
 protected:
  void TrainS3GaussianCheckpoint(const std::string& name, size_t n, uint64_t seed, int64_t steps, int64_t dt_us) {
    dir = testing::ScratchDir("streetsim_grow_extension", name);
    st = RandomState(n, seed);
    canonical = st;
    absl::StatusOr<std::unique_ptr<DynamicStage>> stage = DynamicStage::Begin(&st, s3, {0, 1'000'000});
    ASSERT_TRUE(stage.ok()) << stage.status();
    for (int64_t i = 1; i <= steps; ++i) Step(**stage, st, i, dt_us * i, pool);
    ASSERT_TRUE((*stage)->SaveCheckpoint(FieldCheckpointPath(dir, steps)).ok());
  }
  void TearDown() override {
    if (!dir.empty()) std::filesystem::remove_all(dir);
  }

  ThreadPool pool{2};
  FieldOptions s3 = fixtures::TinyFieldOptions(4);
  std::string dir;
  TrainState st, canonical;  // the trained state; the Gaussians before the field's steps
};

struct Deformed {
  std::vector<float> means, log_scales, rotations, opacity_logits, sh;
};
Deformed Snapshot(const GaussianParamsView& v) {
  return {std::vector<float>(v.means, v.means + v.n * 3), std::vector<float>(v.log_scales, v.log_scales + v.n * 3),
          std::vector<float>(v.rotations, v.rotations + v.n * 4),
          std::vector<float>(v.opacity_logits, v.opacity_logits + v.n),
          std::vector<float>(v.sh, v.sh + v.n * static_cast<size_t>(v.sh_stride) * 3)};
}

TEST_F(GrowExtension, GrownModulesDeformAsTheCheckpointsFieldDid) {
  ASSERT_NO_FATAL_FAILURE(TrainS3GaussianCheckpoint("deform", 2000, 7, 3, 250'000));
  const std::string ckpt = FieldCheckpointPath(dir, 3);

  absl::StatusOr<std::unique_ptr<DynamicStage>> plain = DynamicStage::Resume(ckpt, s3, 3);
  ASSERT_TRUE(plain.ok()) << plain.status();
  absl::StatusOr<GaussianParamsView> pv = (*plain)->Deform(st, 3, 600'000, pool);
  ASSERT_TRUE(pv.ok());
  const Deformed before = Snapshot(*pv);

  FieldOptions grow = s3;
  absl::StatusOr<field::ExtendedFieldConfig> all = field::ExtendedFieldConfig::WithModules("all");
  ASSERT_TRUE(all.ok());
  grow.extended = *all;
  grow.grow_extension = true;
  absl::StatusOr<std::unique_ptr<DynamicStage>> grown = DynamicStage::Resume(ckpt, grow, 3);
  ASSERT_TRUE(grown.ok()) << grown.status();
  ASSERT_NE((*grown)->extended(), nullptr);
  EXPECT_EQ((*grown)->extension_from_fine_iteration(), 3);
  absl::StatusOr<GaussianParamsView> gv = (*grown)->Deform(st, 3, 600'000, pool);
  ASSERT_TRUE(gv.ok()) << gv.status();
  const Deformed after = Snapshot(*gv);

  // The field moved the Gaussians (else the comparison below says nothing) ...
  double moved = 0;
  for (size_t i = 0; i < before.means.size(); ++i)
    moved = std::max(moved, double(std::abs(before.means[i] - canonical.params.means[i])));
  EXPECT_GT(moved, 1e-4);
  // ... and the grown field moves them the same way, up to the extended path's other summation
  // order (as --field-modules none against s3gaussian, tests/field/ext_cli_test.cc).
  ASSERT_EQ(after.means.size(), before.means.size());
  for (size_t i = 0; i < before.means.size(); ++i) ASSERT_NEAR(after.means[i], before.means[i], 1e-5) << i;
  ASSERT_EQ(after.sh.size(), before.sh.size());
  for (size_t i = 0; i < before.sh.size(); ++i) ASSERT_NEAR(after.sh[i], before.sh[i], 1e-5) << i;
  // The decoder's heads start at zero: scales, rotations and opacities are the canonical ones.
  EXPECT_EQ(after.log_scales, canonical.params.log_scales);
  EXPECT_EQ(after.rotations, canonical.params.rotations);
  EXPECT_EQ(after.opacity_logits, canonical.params.opacity_logits);
}

TEST_F(GrowExtension, ResumesCountTheExtensionFromWhereItJoined) {
  ASSERT_NO_FATAL_FAILURE(TrainS3GaussianCheckpoint("resume", 500, 8, 2, 300'000));

  FieldOptions grow = s3;
  absl::StatusOr<field::ExtendedFieldConfig> decoder = field::ExtendedFieldConfig::WithModules("decoder");
  ASSERT_TRUE(decoder.ok());
  grow.extended = *decoder;
  grow.grow_extension = true;
  absl::StatusOr<std::unique_ptr<DynamicStage>> grown = DynamicStage::Resume(FieldCheckpointPath(dir, 2), grow, 2);
  ASSERT_TRUE(grown.ok()) << grown.status();
  for (int64_t i = 3; i <= 5; ++i) Step(**grown, st, i, 150'000 * i, pool);
  ASSERT_TRUE((*grown)->SaveCheckpoint(FieldCheckpointPath(dir, 5)).ok());

  FieldOptions resume = grow;
  resume.grow_extension = false;
  resume.extension_from_fine_iteration = 2;  // as checkpoint.json records it
  absl::StatusOr<std::unique_ptr<DynamicStage>> again = DynamicStage::Resume(FieldCheckpointPath(dir, 5), resume, 5);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ((*again)->extension_from_fine_iteration(), 2);
  EXPECT_EQ((*again)->extended()->params(), (*grown)->extended()->params());

  // Without the record the extension's 3 Adam steps do not match 5 fine iterations.
  resume.extension_from_fine_iteration = 0;
  absl::StatusOr<std::unique_ptr<DynamicStage>> unrecorded =
      DynamicStage::Resume(FieldCheckpointPath(dir, 5), resume, 5);
  ASSERT_FALSE(unrecorded.ok());
  EXPECT_NE(unrecorded.status().message().find("3 fine iterations"), std::string::npos) << unrecorded.status();
  // A record beyond the checkpoint is refused too.
  resume.extension_from_fine_iteration = 6;
  EXPECT_FALSE(DynamicStage::Resume(FieldCheckpointPath(dir, 5), resume, 5).ok());
  // Growing again on a checkpoint that has an extension would throw the trained one away.
  absl::StatusOr<std::unique_ptr<DynamicStage>> regrow = DynamicStage::Resume(FieldCheckpointPath(dir, 5), grow, 5);
  ASSERT_FALSE(regrow.ok());
  EXPECT_NE(regrow.status().message().find("already has an extension"), std::string::npos) << regrow.status();
  // And an extended resume whose extension file is gone is an error, not a fresh extension.
  std::filesystem::remove(ExtendedCheckpointPath(FieldCheckpointPath(dir, 5)));
  resume.extension_from_fine_iteration = 2;
  EXPECT_FALSE(DynamicStage::Resume(FieldCheckpointPath(dir, 5), resume, 5).ok());
}

TEST_F(GrowExtension, TheExtensionStepsAtItsOwnRate) {
  // --field-ext-lr-scale / --field-ext-lr-decay-iterations (ExtHyper) set the modules' Adam rate,
  // apart from the base field's: Adam's first step moves each parameter with a gradient by exactly
  // the rate, so the largest change after one grown iteration is ExtNetworkLr at that iteration.
  ASSERT_NO_FATAL_FAILURE(TrainS3GaussianCheckpoint("rate", 400, 9, 2, 300'000));

  absl::StatusOr<field::ExtendedFieldConfig> decoder = field::ExtendedFieldConfig::WithModules("decoder");
  ASSERT_TRUE(decoder.ok());
  for (const auto& [scale, decay] : {std::pair{1.0, 30000}, {0.04, 4}}) {
    FieldOptions grow = s3;
    grow.extended = *decoder;
    grow.grow_extension = true;
    grow.ext_hyper.lr_scale = scale;
    grow.ext_hyper.lr_decay_steps = decay;
    TrainState run = st;
    absl::StatusOr<std::unique_ptr<DynamicStage>> grown = DynamicStage::Resume(FieldCheckpointPath(dir, 2), grow, 2);
    ASSERT_TRUE(grown.ok()) << grown.status();
    const std::vector<float> before = (*grown)->extended()->params();
    Step(**grown, run, 3, 450'000, pool);
    const std::vector<float>& after = (*grown)->extended()->params();
    ASSERT_EQ(after.size(), before.size());
    double largest = 0;
    for (size_t i = 0; i < before.size(); ++i) largest = std::max(largest, double(std::abs(after[i] - before[i])));
    const double lr = field::ExtNetworkLr(grow.ext_hyper, 3);
    EXPECT_NEAR(largest, lr, 1e-2 * lr) << "scale " << scale << " decay " << decay;
  }
  // The paper's rate at fine iteration 3, and 0.04 x its final rate once the decay of 4 is past.
  EXPECT_NEAR(field::ExtNetworkLr(field::ExtHyper{}, 3), 1.6e-3 * std::pow(0.1, 3.0 / 30000), 1e-12);
  field::ExtHyper annealed;
  annealed.lr_scale = 0.04;
  annealed.lr_decay_steps = 4;
  EXPECT_NEAR(field::ExtNetworkLr(annealed, 5), 0.04 * 1.6e-4, 1e-12);
}

}  // namespace
}  // namespace streetsim::train
