// DIR/checkpoint.json, written beside every checkpoint: the iteration, which field the checkpoint
// holds and the settings it trained with. A run's config is DIR/config.json
// (scene/train/config/run_config.h); this record is the checkpoint's own state (the field, where
// an extended field's modules joined) and what MigrateCheckpointRecord reads in directories from
// before config.json.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "scene/train/divergence_guard.h"

namespace streetsim::train {

inline constexpr char kCheckpointRunFile[] = "checkpoint.json";

// The field's learning-rate schedule (FieldHyper::lr_scale / lr_decay_steps).
struct FieldLrSchedule {
  double scale = 1.0;
  int decay_iterations = 30000;
};

// Low resolution first (resolution_schedule.h): iterations 1..iterations at resolution_scale,
// the rest of the run at TrainOptions::resolution_scale.
struct LowResStage {
  double resolution_scale = 0.25;
  int64_t iterations = 0;
};

// Camera pose refinement's schedule, a copy of the run's Hyper::pose_* (the defaults live there):
// the rates per Adam step and the iterations between which the corrections move (until 0: to the
// run's end).
struct PoseRefinementSchedule {
  double rotation_lr = 0, translation_lr = 0;
  int from = 0;
  int64_t until = 0;
};

struct CheckpointRun {
  int64_t iteration = 0;
  std::string field = "static";  // "static", "s3gaussian" or "extended"
  // A run with a field (its static warm-up included): the warm-up's length and the schedule.
  std::optional<int> static_iterations;
  std::optional<FieldLrSchedule> field_lr;
  std::optional<LowResStage> low_res;                     // a run's low-resolution stage
  std::optional<PoseRefinementSchedule> pose_refinement;  // a run that refines its camera poses
  int position_lr_decay_iterations = 30000;               // Hyper::lr_decay_steps
  int densify_until = 25000;                              // Hyper::densify_until (a stage's iterations)
  // An extended run whose modules were grown on an S3Gaussian run's resume: the fine iteration
  // they joined at (FieldOptions::extension_from_fine_iteration; 0 is not written).
  int64_t field_extension_from = 0;
  // An extended run: the extension's network group (ExtHyper::lr_scale / lr_decay_steps).
  std::optional<FieldLrSchedule> field_ext_lr;
  // A run with a field: the LiDAR motion prior's weight (MotionPriorOptions::weight; 0: off).
  std::optional<double> field_motion_prior;
  // ... and which of an object's scans assign Gaussians (MotionPriorOptions::all_scans), written as
  // `field_motion_prior_scans`: "last" or "all".
  std::optional<bool> field_motion_prior_all_scans;
  // The divergence guard's state at the checkpoint (divergence_guard.h), written as `guard`.
  std::optional<DivergenceGuardState> guard;
};

absl::Status WriteCheckpointRun(const std::string& dir, const CheckpointRun& run);

// The field of the run that wrote DIR/checkpoint.json. NotFound where a run directory predates
// the file; DataLoss where it is damaged.
absl::StatusOr<std::string> ReadCheckpointField(const std::string& dir);

// The fine iteration an extended run's modules joined at (`field_extension_from`): 0 where the
// file does not record one (they joined with the fine stage); NotFound without the file; DataLoss
// where damaged or negative.
absl::StatusOr<int64_t> ReadCheckpointExtensionFrom(const std::string& dir);

// The divergence guard's state the file records for the checkpoint of `iteration`: nullopt where
// it records none, another iteration's, or the file is missing or damaged (the guard then starts
// afresh: a missing record never stops a run).
std::optional<DivergenceGuardState> ReadCheckpointGuard(const std::string& dir, int64_t iteration);

}  // namespace streetsim::train
