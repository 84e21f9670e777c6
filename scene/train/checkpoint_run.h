// DIR/checkpoint.json, written beside every checkpoint: which field the run trains and with what
// learning-rate schedule, so that a resume that does not say keeps them (client/cli/train_command.cc,
// docs/training.md "Default field" and "Field learning rates").
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

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
};

absl::Status WriteCheckpointRun(const std::string& dir, const CheckpointRun& run);

// The field of the run that wrote DIR/checkpoint.json. NotFound where a run directory predates
// the file; DataLoss where it is damaged.
absl::StatusOr<std::string> ReadCheckpointField(const std::string& dir);

// The field's learning-rate schedule the file records (`field_lr_scale`,
// `field_lr_decay_iterations`). nullopt where the file predates them (such runs trained with the
// spec's 1 and 30000) or the run is static; NotFound without the file; DataLoss where damaged or
// out of range.
absl::StatusOr<std::optional<FieldLrSchedule>> ReadCheckpointFieldLr(const std::string& dir);

// The field's learning-rate schedule DIR/train_meta.json records, where that file was written at
// the iteration of DIR/checkpoint.bin (a run segment that ended there): runs trained between
// --field-lr-scale and checkpoint.json's record of it have it only there. nullopt where the file
// is missing, from another iteration or without the schedule; DataLoss where damaged.
absl::StatusOr<std::optional<FieldLrSchedule>> ReadTrainMetaFieldLr(const std::string& dir);

// The low-resolution stage the file records (`low_res_scale`, `low_res_iterations`); nullopt
// where the run has none or the file predates them; NotFound without the file; DataLoss where
// damaged or out of range.
absl::StatusOr<std::optional<LowResStage>> ReadCheckpointLowResStage(const std::string& dir);

// The pose refinement schedule the file records (`pose_rotation_lr`, `pose_translation_lr`,
// `pose_refine_from`, `pose_refine_until`); nullopt where the run does not refine its poses or the
// file predates the record; NotFound without the file; DataLoss where damaged or out of range.
absl::StatusOr<std::optional<PoseRefinementSchedule>> ReadCheckpointPoseRefinement(const std::string& dir);

// The Gaussian means' learning-rate decay the file records (`position_lr_decay_iterations`);
// nullopt where the file predates the record (such runs decayed over 3DGS's 30 000); NotFound
// without the file; DataLoss where damaged or out of range.
absl::StatusOr<std::optional<int>> ReadCheckpointPositionLrDecay(const std::string& dir);

// The stage iteration densification runs until (`densify_until`); nullopt where the file predates
// the record (such runs densified until 25 000); NotFound without the file; DataLoss where damaged
// or out of range.
absl::StatusOr<std::optional<int>> ReadCheckpointDensifyUntil(const std::string& dir);

// The extension's network learning-rate schedule the file records (`field_ext_lr_scale`,
// `field_ext_lr_decay_iterations`). nullopt where the run is not extended or the file predates the
// record (such runs trained at ExtHyper's defaults); NotFound without the file; DataLoss where
// damaged or out of range.
absl::StatusOr<std::optional<FieldLrSchedule>> ReadCheckpointExtLr(const std::string& dir);

// The LiDAR motion prior's weight the file records (`field_motion_prior`): nullopt where the run
// is static or the file predates the record (such runs had no prior); NotFound without the file;
// DataLoss where damaged or out of range.
absl::StatusOr<std::optional<double>> ReadCheckpointMotionPrior(const std::string& dir);

// Whether the motion prior assigned from all of an object's scans (`field_motion_prior_scans`:
// "all" or "last"): nullopt where the file predates the record (such runs used the last scan);
// NotFound without the file; DataLoss where damaged.
absl::StatusOr<std::optional<bool>> ReadCheckpointMotionPriorAllScans(const std::string& dir);

// The fine iteration an extended run's modules joined at (`field_extension_from`): 0 where the
// file does not record one (they joined with the fine stage); NotFound without the file; DataLoss
// where damaged or negative.
absl::StatusOr<int64_t> ReadCheckpointExtensionFrom(const std::string& dir);

}  // namespace streetsim::train
