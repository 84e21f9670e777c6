// A training job's config (server/training_config.h): the trainer's own settings table checks it
// when the job is created (every value `streetsim train` would refuse is INVALID_ARGUMENT naming
// the field or setting), and a valid config becomes exactly the trainer's `--preset` / `--set`
// flags. That those flags are the real trainer's is tested through the built binary in
// tests/server/cli_server_test.cc (JobsTrainPassesTheConfigToTheTrainer).
#include "server/training_config.h"

#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace streetsim::server {
namespace {

v1::TrainingConfig Config(int max_iterations, const std::function<void(v1::TrainingConfig*)>& edit = nullptr) {
  v1::TrainingConfig c;
  c.set_max_iterations(max_iterations);
  if (edit) edit(&c);
  return c;
}

v1::TrainingConfig Settings(std::vector<std::pair<std::string, std::string>> settings, const std::string& preset = "") {
  v1::TrainingConfig c;
  c.set_preset(preset);
  for (auto& [k, v] : settings) (*c.mutable_settings())[k] = v;
  return c;
}

void ExpectRefused(const v1::TrainingConfig& c, const std::string& needle) {
  const absl::Status s = ValidateTrainingConfig(c);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << c.DebugString();
  EXPECT_NE(s.message().find(needle), std::string::npos) << "wanted '" << needle << "' in: " << s.message();
}

TEST(TrainingConfig, PresetAndSettingsBecomeTheTrainersFlags) {
  EXPECT_TRUE(ValidateTrainingConfig(Config(0)).ok());  // init only
  EXPECT_FALSE(AsksTraining(Config(0)));
  const v1::TrainingConfig best = Settings({}, "quality");
  EXPECT_TRUE(AsksTraining(best));
  ASSERT_TRUE(ValidateTrainingConfig(best).ok()) << ValidateTrainingConfig(best);
  EXPECT_EQ(TrainFlags(best), (std::vector<std::string>{"--preset", "quality"}));
  const v1::TrainingConfig c = Settings({{"iterations", "2000"}, {"pose-refinement", "false"}, {"seed", "4"}}, "preview");
  ASSERT_TRUE(ValidateTrainingConfig(c).ok()) << ValidateTrainingConfig(c);
  EXPECT_EQ(TrainFlags(c), (std::vector<std::string>{"--preset", "preview", "--set", "iterations=2000", "--set",
                                                     "pose-refinement=false", "--set", "seed=4"}));
  // Settings without a preset: the default's.
  EXPECT_TRUE(AsksTraining(Settings({{"iterations", "300"}})));
  EXPECT_EQ(TrainFlags(Settings({{"iterations", "300"}})), (std::vector<std::string>{"--set", "iterations=300"}));
}

TEST(TrainingConfig, DeprecatedFieldsAreTheirSettings) {
  const v1::TrainingConfig c = Config(12000, [](v1::TrainingConfig* c) {
    c->set_preset("preview");  // no schedule: clips train in one stage
    c->set_seed(3);
    c->set_field("extended");
    c->set_field_modules("temporal,decoder");
    c->set_static_iterations(4000);
    c->set_resolution_scale(0.1234567891);
    c->set_low_res_scale(0.05);
    c->set_low_res_iterations(3000);
    c->set_holdout_every(0);
    c->set_clip_frames(50);
    c->set_clip_overlap(0);
    c->set_field_lr_scale(2.5);
    c->set_field_lr_decay_iterations(6000);
    c->set_backend("vulkan");
    c->set_pose_refinement(true);
    c->set_pose_lr_scale(3);
    c->set_field_ext_lr_scale(0.4);
    c->set_field_ext_lr_decay_iterations(4500);
    c->set_field_motion_prior(0);  // set, so 0 is a value: off
    c->set_field_motion_prior_scans("all");
    c->set_densify_until(0);
  });
  ASSERT_TRUE(ValidateTrainingConfig(c).ok()) << ValidateTrainingConfig(c);
  EXPECT_EQ(TrainFlags(c),
            (std::vector<std::string>{
                "--preset", "preview", "--set", "iterations=12000", "--set", "seed=3", "--set", "field=extended", "--set",
                "field-modules=temporal,decoder", "--set", "static-iterations=4000", "--set",
                "resolution-scale=0.1234567891", "--set", "low-res-scale=0.05", "--set", "low-res-iterations=3000",
                "--set", "holdout-every=0", "--set", "clip-frames=50", "--set", "clip-overlap=0", "--set",
                "field-lr-scale=2.5", "--set", "field-lr-decay-iterations=6000", "--set", "densify-until=0", "--set",
                "field-ext-lr-scale=0.4", "--set", "field-ext-lr-decay-iterations=4500", "--set",
                "field-motion-prior=0", "--set", "field-motion-prior-scans=all", "--set", "backend=vulkan", "--set",
                "pose-refinement=true", "--set", "pose-lr-scale=3"}));
}

TEST(TrainingConfig, BadValuesAreRefusedNamingTheFieldOrSetting) {
  ExpectRefused(Config(-1), "config.max_iterations");
  ExpectRefused(Config(10'000'001), "config.max_iterations");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_field("static"); }), "max_iterations > 0");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_continue_from_scene("x"); }), "max_iterations > 0");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_field("dynamic"); }),
                "config.field: field must be one of auto, static, s3gaussian, extended, not 'dynamic'");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_modules("all"); }), "needs field extended");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_static_iterations(100); }),
                "static-iterations (100) must be below iterations (100)");
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field("s3gaussian"); }), "must be below iterations");
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(2); }), "needs a field");
  // At its default it asks for nothing: no mistake in a static run.
  EXPECT_TRUE(ValidateTrainingConfig(Config(3000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(10); })).ok());
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(NAN); }), "config.field_lr_scale");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_pose_lr_scale(1001); }), "config.pose_lr_scale");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_densify_until(-1); }),
                "config.densify_until: densify-until must be an integer in 0..10000000");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_motion_prior(INFINITY); }),
                "config.field_motion_prior");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_low_res_scale(0.25); }), "needs low-res-iterations");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_holdout_every(1); }), "holdout-every");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_clip_frames(2); }), "clip-frames");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_backend("cuda"); }), "config.backend");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_continue_from_scene("../scenes/x"); }),
                "config.continue_from_scene");
  // The new fields: an unknown setting, a wrong type, out of range, an unknown preset.
  ExpectRefused(Settings({{"warp", "1"}}), "config.settings['warp']: unknown setting 'warp'");
  ExpectRefused(Settings({{"iterations", "many"}}), "iterations must be an integer in 1..10000000, not 'many'");
  ExpectRefused(Settings({{"resolution-scale", "7"}}), "resolution-scale must be a number in (0, 1]");
  ExpectRefused(Settings({}, "fastest"), "no preset 'fastest' (presets: quality, preview)");
  ExpectRefused(Settings({{std::string("\x01\xff", 2), "1"}}), "unknown setting");
  v1::TrainingConfig many;
  for (int i = 0; i < 300; ++i) (*many.mutable_settings())["s" + std::to_string(i)] = "1";
  ExpectRefused(many, "more than 256");
  // A continuation keeps its scene's config: settings are checked one by one, a preset refused.
  const v1::TrainingConfig anneal = Config(100, [](v1::TrainingConfig* c) {
    c->set_continue_from_scene("kitti_full");
    c->set_field_lr_decay_iterations(600);
    c->set_densify_until(0);
  });
  EXPECT_TRUE(ValidateTrainingConfig(anneal).ok()) << ValidateTrainingConfig(anneal);
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_continue_from_scene("kitti_full");
                  c->set_preset("preview");
                }),
                "a continuation keeps its scene's config");
}

}  // namespace
}  // namespace streetsim::server
