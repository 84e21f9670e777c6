// The training settings: the one table that declares them (train_settings.cc) and the trainer's
// options they resolve to. `streetsim train`'s flags, `--set`, config files and presets, the
// server's training jobs and DIR/config.json all read and check values through it
// (docs/training.md "Settings"; adding a setting: docs/contributing.md).
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/train/clip_training.h"
#include "scene/train/config/setting.h"
#include "scene/train/trainer.h"

namespace streetsim::train::config {

// What a resolved config sets: the trainer's options and the clip plan.
struct TrainRunOptions {
  TrainOptions train;
  ClipTrainOptions clips;
  // `field auto` chose S3Gaussian's field (the run is longer than its static stage).
  bool field_chosen_by_default = false;
};

// The declarations, in the order help lists them.
const std::vector<SettingDef>& TrainSettingDefs();

// The settings only a field run uses (given in a static run: InvalidArgument).
const std::vector<std::string>& FieldOnlySettings();

// Pose refinement's switch and the settings that tune it.
const std::vector<std::string>& PoseSettings();

// Every setting at its declared default.
Settings DefaultTrainSettings();

// The trainer's options for these values: each setting's apply, then the settings that depend on
// others (`field auto`, the pose schedule's end, the low-resolution pair). InvalidArgument naming
// the settings when values the user gave contradict each other (e.g. a field setting in a static
// run, `static-iterations` not below `iterations`).
// segment_end > 0: the options of the run's segment that ends there (a schedule's stage,
// run_config.h): the trainer runs to that iteration, and a segment within the static stage of a
// field run trains the static model, as the run does there.
absl::StatusOr<TrainRunOptions> ResolveTrainOptions(const Settings& settings, int64_t segment_end = 0);

}  // namespace streetsim::train::config
