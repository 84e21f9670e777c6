// A training job's config (server/training_config.h): every value `streetsim train` would refuse is
// refused when the job is created, naming the field; a valid config becomes exactly the trainer's
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

void ExpectRefused(const v1::TrainingConfig& c, const std::string& needle) {
  const absl::Status s = ValidateTrainingConfig(c);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << c.DebugString();
  EXPECT_NE(s.message().find(needle), std::string::npos) << "wanted '" << needle << "' in: " << s.message();
}

TEST(TrainingConfig, DefaultsAreValidAndAddNoFlags) {
  EXPECT_TRUE(ValidateTrainingConfig(Config(0)).ok());
  EXPECT_TRUE(ValidateTrainingConfig(Config(300)).ok());
  EXPECT_TRUE(ValidateTrainingConfig(Config(30000)).ok());
  EXPECT_TRUE(TrainFlags(Config(300)).empty());
  EXPECT_EQ(TrainFlags(Config(300, [](v1::TrainingConfig* c) { c->set_seed(7); })),
            (std::vector<std::string>{"--seed", "7"}));
}

TEST(TrainingConfig, EveryOptionBecomesTheTrainersFlag) {
  const v1::TrainingConfig c = Config(12000, [](v1::TrainingConfig* c) {
    c->set_seed(3);
    c->set_field("extended");
    c->set_field_modules("temporal,decoder");
    c->set_static_iterations(4000);
    c->set_resolution_scale(0.5);
    c->set_low_res_scale(0.25);
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
    c->set_field_motion_prior(0.3);
    c->set_field_motion_prior_scans("all");
  });
  ASSERT_TRUE(ValidateTrainingConfig(c).ok()) << ValidateTrainingConfig(c);
  EXPECT_EQ(TrainFlags(c), (std::vector<std::string>{
                               "--seed", "3", "--field", "extended", "--field-modules", "temporal,decoder",
                               "--static-iterations", "4000", "--resolution-scale", "0.5", "--low-res-scale", "0.25",
                               "--low-res-iterations", "3000", "--holdout-every", "0", "--clip-frames", "50",
                               "--clip-overlap", "0", "--field-lr-scale", "2.5", "--field-lr-decay-iterations", "6000",
                               "--field-ext-lr-scale", "0.4", "--field-ext-lr-decay-iterations", "4500",
                               "--field-motion-prior", "0.3", "--field-motion-prior-scans", "all", "--backend",
                               "vulkan", "--pose-refinement",
                               "--pose-lr-scale", "3"}));
  // Numbers go to the trainer exactly (not rounded to 6 digits).
  const v1::TrainingConfig exact = Config(300, [](v1::TrainingConfig* c) { c->set_resolution_scale(0.1234567891); });
  EXPECT_EQ(TrainFlags(exact), (std::vector<std::string>{"--resolution-scale", "0.1234567891"}));
  // Unset optional fields are the trainer's defaults, not 0; a set 0 is passed on (a continuation
  // that turns the scene's motion prior off).
  const v1::TrainingConfig off = Config(9000, [](v1::TrainingConfig* c) { c->set_field_motion_prior(0); });
  ASSERT_TRUE(ValidateTrainingConfig(off).ok()) << ValidateTrainingConfig(off);
  EXPECT_EQ(TrainFlags(off), (std::vector<std::string>{"--field-motion-prior", "0"}));
  const v1::TrainingConfig d = Config(300, [](v1::TrainingConfig* c) { c->set_clip_frames(20); });
  EXPECT_EQ(TrainFlags(d), (std::vector<std::string>{"--clip-frames", "20"}));
}

TEST(TrainingConfig, BadValuesAreRefusedNamingTheField) {
  ExpectRefused(Config(-1), "config.max_iterations");
  ExpectRefused(Config(10'000'001), "config.max_iterations");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_field("static"); }), "max_iterations > 0");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_holdout_every(4); }), "max_iterations > 0");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_field("dynamic"); }), "config.field must be");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_modules("all"); }),
                "field_modules needs field \"extended\"");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) {
                  c->set_field("extended");
                  c->set_field_modules("encoder,warp");
                }),
                "config.field_modules");
  // The static warm-up must end before the run does, and a static run has no field to train.
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_static_iterations(100); }), "0..99");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_static_iterations(-1); }), "0..99");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_field("static");
                  c->set_static_iterations(50);
                }),
                "static_iterations needs a field");
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field("s3gaussian"); }), "set static_iterations");
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(10); }), "need a field");
  EXPECT_TRUE(ValidateTrainingConfig(Config(3000, [](v1::TrainingConfig* c) {
                c->set_static_iterations(2000);
                c->set_field_lr_scale(10);
              })).ok());
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(-1); }), "field_lr_scale");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(1001); }), "field_lr_scale");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_lr_scale(NAN); }), "field_lr_scale");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_pose_lr_scale(2); }), "needs pose_refinement");
  for (double bad : {-1.0, 1001.0, double(NAN)}) {
    ExpectRefused(Config(9000, [&](v1::TrainingConfig* c) {
                    c->set_pose_refinement(true);
                    c->set_pose_lr_scale(bad);
                  }),
                  "config.pose_lr_scale");
  }
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_pose_refinement(true); }), "max_iterations > 0");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_lr_decay_iterations(-5); }),
                "field_lr_decay_iterations");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_position_lr_decay_iterations(-1); }),
                "config.position_lr_decay_iterations");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_position_lr_decay_iterations(500); }),
                "max_iterations > 0");
  for (int bad : {-1, 10'000'001}) {
    ExpectRefused(Config(9000, [&](v1::TrainingConfig* c) { c->set_densify_until(bad); }),
                  "config.densify_until must be in 0..10000000");
  }
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_densify_until(0); }), "max_iterations > 0");
  // The modules' rate: field "extended" only (a continuation must say so, as the trainer's resume does).
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_ext_lr_scale(0.5); }), "need field \"extended\"");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) {
                  c->set_field("s3gaussian");
                  c->set_field_ext_lr_decay_iterations(600);
                }),
                "need field \"extended\"");
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) {
                  c->set_continue_from_scene("kitti_full");
                  c->set_field_ext_lr_scale(0.5);
                }),
                "need field \"extended\"");
  for (double bad : {-1.0, 1001.0, double(NAN)}) {
    ExpectRefused(Config(9000, [&](v1::TrainingConfig* c) {
                    c->set_field("extended");
                    c->set_field_ext_lr_scale(bad);
                  }),
                  "config.field_ext_lr_scale");
  }
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) {
                  c->set_field("extended");
                  c->set_field_ext_lr_decay_iterations(-3);
                }),
                "config.field_ext_lr_decay_iterations");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_field_ext_lr_scale(0.5); }), "max_iterations > 0");
  // The motion prior: a field's, in [0, 10000].
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field_motion_prior(0.3); }), "needs a field");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_field_motion_prior(0.3); }), "max_iterations > 0");
  for (double bad : {-0.1, 10001.0, double(NAN), double(INFINITY)}) {
    ExpectRefused(Config(9000, [&](v1::TrainingConfig* c) { c->set_field_motion_prior(bad); }),
                  "config.field_motion_prior");
  }
  ExpectRefused(Config(9000, [](v1::TrainingConfig* c) { c->set_field_motion_prior_scans("some"); }),
                "config.field_motion_prior_scans");
  ExpectRefused(Config(3000, [](v1::TrainingConfig* c) { c->set_field_motion_prior_scans("all"); }), "needs a field");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_field_motion_prior_scans("all"); }), "max_iterations > 0");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_resolution_scale(1.5); }), "resolution_scale");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_resolution_scale(-0.5); }), "resolution_scale");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_resolution_scale(INFINITY); }), "resolution_scale");
  // The low-resolution stage: both values, a scale below the run's, ending before the run.
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_low_res_scale(0.25); }), "go together");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_low_res_iterations(50); }), "go together");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_resolution_scale(0.25);
                  c->set_low_res_scale(0.5);
                  c->set_low_res_iterations(50);
                }),
                "config.low_res_scale / low_res_iterations");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_low_res_scale(0.25);
                  c->set_low_res_iterations(100);
                }),
                "config.low_res_scale / low_res_iterations");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_low_res_scale(NAN);
                  c->set_low_res_iterations(50);
                }),
                "low_res_scale");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_holdout_every(1); }), "holdout_every");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_holdout_every(-2); }), "holdout_every");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_clip_frames(2); }), "config.clip_frames");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_clip_frames(-1); }), "config.clip_frames");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_clip_overlap(2); }), "clip_overlap needs clip_frames");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) {
                  c->set_clip_frames(20);
                  c->set_clip_overlap(11);
                }),
                "config.clip_overlap");
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_backend("cuda"); }), "config.backend");
  // A continuation names a scene, never a path; its field is the scene's (the job runner checks
  // that one), so field-dependent options pass here.
  ExpectRefused(Config(100, [](v1::TrainingConfig* c) { c->set_continue_from_scene("../scenes/x"); }),
                "config.continue_from_scene");
  ExpectRefused(Config(0, [](v1::TrainingConfig* c) { c->set_continue_from_scene("x"); }), "max_iterations > 0");
  const v1::TrainingConfig anneal = Config(100, [](v1::TrainingConfig* c) {
    c->set_continue_from_scene("kitti_full");
    c->set_field_lr_decay_iterations(600);
    c->set_position_lr_decay_iterations(700);
    c->set_densify_until(0);  // set, so 0 is a value: no more densification
  });
  EXPECT_TRUE(ValidateTrainingConfig(anneal).ok()) << ValidateTrainingConfig(anneal);
  EXPECT_EQ(TrainFlags(anneal),
            (std::vector<std::string>{"--field-lr-decay-iterations", "600", "--position-lr-decay-iterations", "700",
                                      "--densify-until", "0"}));
}

}  // namespace
}  // namespace streetsim::server
