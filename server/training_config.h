// A training job's TrainingConfig (proto/streetsim/v1/training.proto): its checks and the
// `streetsim train` flags it stands for. The job runner spawns the trainer; this module is where
// the config meets the trainer's flags, so that both stay in one place on the server side.
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "streetsim/v1/training.pb.h"

namespace streetsim::server {

// INVALID_ARGUMENT (naming the config field or setting) for any value `streetsim train` would
// refuse with exit 2: checked when the job is created, not when its train stage starts, by the
// trainer's own settings table and resolution (scene/train/config/), so the two cannot disagree.
absl::Status ValidateTrainingConfig(const v1::TrainingConfig& config);

// A scene name a job may produce or continue from: 1-64 of [A-Za-z0-9_.-], not starting with '.'
// (so never a path).
bool IsSceneName(const std::string& name);

// Whether the job has a train stage: it names a preset or settings, or max_iterations > 0.
bool AsksTraining(const v1::TrainingConfig& config);

// The flags after `--log LOG --out DIR` for a config that passed ValidateTrainingConfig:
// `--preset`, then a `--set NAME=VALUE` per setting (the deprecated fields' first, then the
// settings map's). The same on every attempt, so a resumed train stage keeps them.
std::vector<std::string> TrainFlags(const v1::TrainingConfig& config);

}  // namespace streetsim::server
