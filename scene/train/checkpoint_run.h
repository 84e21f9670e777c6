// DIR/checkpoint.json, written beside every checkpoint: the checkpoint's own state (its iteration,
// which field it holds, where an extended field's modules joined, the divergence guard's record).
// A run's settings are DIR/config.json's alone (scene/train/config/run_config.h); directories from
// before config.json also recorded settings here, which MigrateCheckpointRecord reads.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "scene/train/divergence_guard.h"

namespace streetsim::train {

inline constexpr char kCheckpointRunFile[] = "checkpoint.json";

struct CheckpointRun {
  int64_t iteration = 0;
  std::string field = "static";  // "static", "s3gaussian" or "extended"
  // An extended run whose modules were grown on an S3Gaussian run's resume: the fine iteration
  // they joined at (FieldOptions::extension_from_fine_iteration; 0 is not written).
  int64_t field_extension_from = 0;
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
