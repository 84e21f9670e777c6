// What a `streetsim train` command line (or a training job's, which is one) asks for, resolved
// against the run directory: a new run's config (preset, then a config file, then the settings
// given) or a resumed run's (DIR/config.json plus the changes given; docs/training.md
// "Resuming"). The one place that decides what a run trains with.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"
#include "scene/train/config/run_config.h"

namespace streetsim::train::config {

struct CommandLineConfig {
  std::optional<std::string> preset;       // --preset NAME
  std::optional<std::string> config_path;  // --config FILE.json
  // Settings given as flags (`--NAME VALUE`, `--NAME` / `--no-NAME` for a bool) and `--set
  // NAME=VALUE`, in order (a later one wins): (name, text, how it was given, for messages).
  struct Given {
    std::string name, text, what;
  };
  std::vector<Given> values;
};

struct ResolvedRun {
  RunConfig config;
  bool resumes = false;             // a checkpoint or config.json of this run is there
  int64_t done_iterations = 0;      // the checkpoint's iteration (0: none)
  std::vector<std::string> changed;  // a resume's changes (settings that now differ)
  // The directory predates config.json: its config was rebuilt from checkpoint.json
  // (MigrateCheckpointRecord) and the defaults of the time.
  bool migrated = false;
  // `field auto` chose S3Gaussian's field by the run's length alone (a new run; FitFieldToLog).
  bool field_by_length = false;
  // Pose refinement is on by the preset alone: nothing the user gave names a pose setting (a new
  // run; FitPosesToLog).
  bool poses_by_preset = false;
};

// InvalidArgument naming the setting or file for bad values, unknown settings, a missing or
// unknown preset, a --preset that differs from a resumed run's, a schedule on a resume, and
// contradicting settings; DataLoss naming DIR/config.json when it is damaged.
absl::StatusOr<ResolvedRun> ResolveRun(const std::string& out_dir, bool resume, const CommandLineConfig& given);

// What `field auto` chose by the run's length, checked against the log once it is open: a log
// without LiDAR (camera only) trains the static model. Measured on both shared camera-only logs
// (docs/training.md "Presets"): on the odometry excerpt S3Gaussian's field drifts without the
// LiDAR's motion prior and depth and ends ~6 dB below the static model of the same iterations; on
// colmap_plush (a photo collection, no time to follow) the two draw at the same iterations and the
// static model takes a third of the time. Says so in the config's notes (kCameraOnlyStaticNote).
// Only a new run's own choice changes: a field the user asked for (or a resume's) stays. True
// when it made the run static.
absl::StatusOr<bool> FitFieldToLog(const DriveLog& log, ResolvedRun* run);
inline constexpr char kCameraOnlyStaticNote[] =
    "field auto: the static model, as the log has no LiDAR (a camera-only log: docs/training.md \"Presets\")";

// Pose refinement that the preset turned on, checked against the log once it is open: a log whose
// poses were estimated from its own images (a COLMAP model, bundle-adjusted against them) trains at
// those poses. Refining them moved the training views off poses that were already consistent with
// the images, and the held-out views, which take their neighbours' corrections, lost 1.2-1.9 dB on
// colmap_plush; on the odometry excerpt's recorded poses refinement gained 1.0-1.4 dB, on the KITTI
// clip's GNSS/INS poses 1.2 dB (docs/training.md "Presets"). A user's pose setting (or a resume's
// record) stays. Says so in the config's notes (kImagePosesNote); true when it turned it off.
absl::StatusOr<bool> FitPosesToLog(const DriveLog& log, ResolvedRun* run);
inline constexpr char kImagePosesNote[] =
    "pose refinement: off, as the log's poses were estimated from its own images (COLMAP): docs/training.md "
    "\"Presets\"";

// A run directory from before config.json: its config from DIR/checkpoint.json's records (the
// settings they name, under their own names with '-' for '_') on the trainer's defaults of the
// time (the table's). Without checkpoint.json (older still): the field from the field
// checkpoints present. DataLoss naming the file where it is damaged.
absl::StatusOr<RunConfig> MigrateCheckpointRecord(const std::string& out_dir);

}  // namespace streetsim::train::config
