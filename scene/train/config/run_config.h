// A training run's whole config: the settings it starts from, its schedule of stages and the
// preset it came from; read from presets and config files, written once as DIR/config.json when
// the run starts and read back by `--resume` (docs/training.md "Settings", "Schedules").
//
// A schedule is a list of stages. Stage k starts after iteration `from` (the first from 0) and
// changes the settings its `set` names from then on (a later stage's set adds to the earlier
// ones'). Every stage start is a segment end: the run writes its outputs there (scene, held-out
// figures) as a run of that length would, and goes on from its checkpoint with the next stage's
// settings, in the same process. So a schedule is what a sequence of `--resume` runs did, as one
// run that can be stopped and resumed at any iteration.
#pragma once

#include <cstdint>
#include <map>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/train/config/setting.h"

namespace streetsim::train::config {

inline constexpr int kConfigSchemaVersion = 1;
inline constexpr char kRunConfigFileName[] = "config.json";
inline constexpr char kDefaultPreset[] = "quality";

struct ScheduleStage {
  int64_t from = 0;
  std::map<std::string, SettingValue> set;
  // The names in `set` the user gave (a resume's changes): checked against the other settings
  // from this stage on, as given values are (Origin::kGiven).
  std::set<std::string> given = {};
};

struct RunConfig {
  RunConfig();
  std::string preset;  // the preset the run started from ("" none)
  Settings settings;   // the values before any stage's set (every setting)
  std::vector<ScheduleStage> schedule;  // increasing `from`, the first from 0; empty: one stage
  // What happened to the run that changed its config (the divergence guard's rollbacks), one
  // line each, in order.
  std::vector<std::string> notes;
};

// One segment of a run: its last iteration and the settings in force up to it.
struct Segment {
  int64_t end = 0;
  Settings settings;
};

// The segments of the run to its `iterations` (as of the settings in force at the end).
std::vector<Segment> Segments(const RunConfig& config);

// The preset's config; InvalidArgument naming the known presets when there is no such preset.
absl::StatusOr<RunConfig> PresetConfig(const std::string& name);
std::vector<std::string> PresetNames();
// A preset's one-line description (its file's "description").
std::string PresetDescription(const std::string& name);

// Applies a config document ({"schema_version": 1, "settings": {...}, "schedule": [...]}; a
// preset's or a --config file's) on top of *config: its settings as `origin`, its schedule (if
// any) replacing the config's. `source` names it in errors (InvalidArgument for a wrong value,
// an unknown key or a future schema version).
absl::Status ApplyConfigDocument(const std::string& text, Origin origin, const std::string& source,
                                 RunConfig* config);

// Settings the user gave for a new run hold for the whole run: the preset's stages stop setting
// them.
void HoldThroughSchedule(const std::set<std::string>& names, RunConfig* config);

// A resumed run's changes (settings given on its command line that differ from those in force
// after `iteration`): from `iteration` on, to the end of the run (later stages stop setting
// them); `iterations`, the run's end, changes the run itself. Returns the names that changed.
absl::StatusOr<std::vector<std::string>> ChangeFrom(int64_t iteration, const Settings& given,
                                                    const std::set<std::string>& given_names, RunConfig* config);

// DIR/config.json: the resolved config, written atomically. Reading it: NotFound without the
// file; DataLoss (naming the file) when damaged; InvalidArgument for another schema version.
absl::Status WriteRunConfig(const std::string& dir, const RunConfig& config);
absl::StatusOr<RunConfig> ReadRunConfig(const std::string& dir);
std::string RunConfigJson(const RunConfig& config);

}  // namespace streetsim::train::config
