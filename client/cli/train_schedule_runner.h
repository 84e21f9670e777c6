// Runs a resolved training config (scene/train/config/) in one process: its segments in turn,
// each a `TrainClips` call that goes on from its predecessor's checkpoint; records the config
// once the trainer has taken it; and the divergence guard's rollbacks (docs/training.md
// "Schedules", "Divergence guard"). `streetsim train` (train_command.cc) is its one caller.
#pragma once

#include <atomic>
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"
#include "scene/train/clip_training.h"
#include "scene/train/config/run_resolution.h"

namespace streetsim {

// The run's segments from its checkpoint on; `progress` gets the trainer's progress (iterations
// of the whole run). The last segment's result, or the status the run stops with (Cancelled for
// a stop request, Aborted for a divergence the guard could not roll back).
absl::StatusOr<train::ClipTrainResult> RunSchedule(const DriveLog& log, const std::string& out_dir,
                                                   const std::atomic<bool>* stop_requested,
                                                   const std::function<void(const train::Progress&)>& progress,
                                                   train::config::ResolvedRun* run);

}  // namespace streetsim
