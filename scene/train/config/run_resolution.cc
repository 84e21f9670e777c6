#include "scene/train/config/run_resolution.h"

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <set>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "scene/common/checked_file.h"
#include "scene/log/colmap_reader.h"
#include "scene/train/checkpoint_run.h"
#include "scene/train/config/train_settings.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/train_state.h"

namespace streetsim::train::config {
namespace {

namespace fs = std::filesystem;

constexpr std::uintmax_t kMaxConfigFileBytes = 1 << 20;

absl::StatusOr<std::string> ReadConfigFile(const std::string& path) {
  absl::StatusOr<std::string> text = checked_file::ReadBounded(path, kMaxConfigFileBytes);
  if (absl::IsOutOfRange(text.status())) {
    return absl::InvalidArgumentError(absl::StrCat("--config ", path, ": larger than 1 MiB, not a config"));
  }
  if (absl::IsNotFound(text.status())) {
    return absl::InvalidArgumentError(absl::StrCat("--config ", path, ": no such file"));
  }
  if (!text.ok()) return absl::InvalidArgumentError(absl::StrCat("--config ", path, ": cannot be read"));
  return text;
}

// The given settings (a config file's, then the flags') on `base`; their names into *names.
absl::Status ApplyGiven(const CommandLineConfig& given, const std::optional<std::string>& file_text,
                        RunConfig* base, std::set<std::string>* names, bool* file_schedule) {
  if (file_text) {
    RunConfig file;
    file.schedule.clear();
    if (absl::Status s = ApplyConfigDocument(*file_text, Origin::kGiven, *given.config_path, &file); !s.ok()) return s;
    for (const SettingDef& d : file.settings.defs()) {
      if (!file.settings.given(d.name)) continue;
      (void)base->settings.Set(d.name, file.settings.Get(d.name), Origin::kGiven, *given.config_path);
      names->insert(d.name);
    }
    *file_schedule = !file.schedule.empty();
    if (*file_schedule) base->schedule = file.schedule;
  }
  for (const CommandLineConfig::Given& g : given.values) {
    if (absl::Status s = base->settings.SetText(g.name, g.text, Origin::kGiven, g.what); !s.ok()) return s;
    names->insert(g.name);
  }
  // Checked on what this command names, not on the resolved run: a resume that ends a recorded
  // low-resolution stage with low-res-iterations 0 keeps the recorded scale, and that is fine.
  if (names->count("low-res-scale") && base->settings.GetInt("low-res-iterations") == 0) {
    return absl::InvalidArgumentError("low-res-scale needs low-res-iterations > 0");
  }
  return absl::OkStatus();
}

// `field auto` resolved to what the run trains, so that a resume that changes its iterations
// keeps its field (a static run grown past 5000 iterations stays static). True when the run's
// length chose the field and nothing the user gave asks for one (FitFieldToLog may undo it).
bool PinField(RunConfig* config) {
  if (config->settings.GetText("field") != "auto") return false;
  const Origin o = config->settings.origin("field");
  const std::vector<Segment> segments = Segments(*config);
  const Settings& last = segments.back().settings;
  const bool field =
      last.given("static-iterations") || last.GetInt("iterations") > last.GetInt("static-iterations");
  (void)config->settings.Set("field", std::string(field ? "s3gaussian" : "static"), o, "field auto");
  if (!field) return false;
  for (const Segment& segment : segments) {
    for (const std::string& name : FieldOnlySettings()) {
      if (segment.settings.given(name)) return false;
    }
  }
  return true;
}

// The poses were estimated from the log's own images (a COLMAP model, bundle-adjusted against
// them), not recorded by a navigation system or LiDAR odometry.
bool PosesFromImages(const DriveLog& log) { return log.pose_source == kColmapPoseSource; }

// Pose refinement is on, and no setting of it was given, for the run or in a stage of its schedule.
bool PosesByPreset(const RunConfig& config) {
  const std::vector<Segment> segments = Segments(config);
  if (!segments.back().settings.GetBool("pose-refinement")) return false;
  for (const Segment& segment : segments) {
    for (const std::string& name : PoseSettings()) {
      if (segment.settings.given(name)) return false;
    }
  }
  return true;
}

// Every segment resolves: the relations between settings hold over the whole run.
absl::Status CheckSegments(const RunConfig& config) {
  const std::vector<Segment> segments = Segments(config);
  if (segments.size() > 1 && segments.back().settings.GetInt("clip-frames") > 0) {
    return absl::InvalidArgumentError(
        "clip-frames: a clip set trains in one stage, and this run's schedule has several (a preset or config "
        "without a schedule, e.g. --preset preview, runs clips)");
  }
  for (const Segment& s : segments) {
    if (absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(s.settings, s.end); !o.ok()) return o.status();
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<RunConfig> MigrateCheckpointRecord(const std::string& out_dir) {
  RunConfig config;
  config.schedule.clear();
  const std::string path = (fs::path(out_dir) / kCheckpointRunFile).string();
  std::ifstream in(path);
  const std::string what = absl::StrCat(path, " (from before config.json)");
  if (!in) {
    const FieldCheckpointsFound found = FindFieldCheckpoints(out_dir);
    const std::string field = found.extended ? "extended" : found.base ? "s3gaussian" : "auto";
    (void)config.settings.Set("field", field, Origin::kPreset, what);
    // Such runs trained their field at S3Gaussian's rates, the only ones then.
    if (found.base || found.extended) (void)config.settings.Set("field-lr-scale", 1.0, Origin::kPreset, what);
    return config;
  }
  nlohmann::json j = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (!j.is_object()) return absl::DataLossError(absl::StrCat(path, " is damaged (not a JSON object)"));
  const Hyper defaults;
  for (const auto& [key, value] : j.items()) {
    if (key == "iteration" || key == "field_extension_from" || key == "pose_translation_lr") continue;
    if (key == "pose_rotation_lr") {  // the rates as a scale of the defaults (both scale together)
      if (!value.is_number() || !(value.get<double>() > 0)) return absl::DataLossError(absl::StrCat(path, ": ", key));
      (void)config.settings.Set("pose-refinement", true, Origin::kPreset, what);
      if (absl::Status s = config.settings.Set("pose-lr-scale", value.get<double>() / defaults.pose_rotation_lr,
                                               Origin::kPreset, what);
          !s.ok()) {
        return absl::DataLossError(s.message());
      }
      continue;
    }
    const std::string name = absl::StrReplaceAll(key, {{"_", "-"}});
    if (config.settings.Find(name) == nullptr) continue;  // a record that is not a setting
    if (absl::Status s = config.settings.SetJson(name, value, Origin::kPreset, what); !s.ok()) {
      return absl::DataLossError(s.message());
    }
  }
  if (!j.contains("field_lr_scale") && config.settings.GetText("field") != "static" &&
      config.settings.GetText("field") != "auto") {
    (void)config.settings.Set("field-lr-scale", 1.0, Origin::kPreset, what);
  }
  return config;
}

absl::StatusOr<ResolvedRun> ResolveRun(const std::string& out_dir, bool resume, const CommandLineConfig& given) {
  std::optional<std::string> file_text;
  if (given.config_path) {
    absl::StatusOr<std::string> t = ReadConfigFile(*given.config_path);
    if (!t.ok()) return t.status();
    file_text = *t;
  }
  ResolvedRun run;
  std::error_code ec;
  const fs::path ckpt = fs::path(out_dir) / "checkpoint.bin";
  const bool has_checkpoint = fs::exists(ckpt, ec);
  if (resume && has_checkpoint) {
    absl::StatusOr<int64_t> done = PeekCheckpointIteration(ckpt.string());
    if (!done.ok()) return done.status();
    run.done_iterations = *done;
  }
  absl::StatusOr<RunConfig> recorded = absl::NotFoundError("new run");
  if (resume) {
    recorded = ReadRunConfig(out_dir);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return recorded.status();
    if (!recorded.ok() && has_checkpoint) {
      recorded = MigrateCheckpointRecord(out_dir);
      if (!recorded.ok()) return recorded.status();
      run.migrated = true;
    }
  }
  std::set<std::string> names;
  bool file_schedule = false;
  if (recorded.ok()) {
    // A resume: the recorded config, with what the command line changes from here on.
    run.resumes = true;
    run.config = std::move(*recorded);
    if (given.preset && *given.preset != run.config.preset) {
      return absl::InvalidArgumentError(absl::StrCat(
          "--preset ", *given.preset, ": ", out_dir, " is a run of ",
          run.config.preset.empty() ? std::string("no preset") : "preset " + run.config.preset,
          "; a resume changes settings with --set NAME=VALUE (or start a new directory)"));
    }
    RunConfig changes;
    changes.settings = run.config.settings;
    if (absl::Status s = ApplyGiven(given, file_text, &changes, &names, &file_schedule); !s.ok()) return s;
    if (file_schedule) {
      return absl::InvalidArgumentError(absl::StrCat("--config ", *given.config_path,
                                                     ": a resumed run keeps its schedule (settings only)"));
    }
    absl::StatusOr<std::vector<std::string>> changed =
        ChangeFrom(run.done_iterations, changes.settings, names, &run.config);
    if (!changed.ok()) return changed.status();
    run.changed = *changed;
  } else {
    absl::StatusOr<RunConfig> preset = PresetConfig(given.preset.value_or(kDefaultPreset));
    if (!preset.ok()) return preset.status();
    run.config = std::move(*preset);
    if (absl::Status s = ApplyGiven(given, file_text, &run.config, &names, &file_schedule); !s.ok()) return s;
    // What the user set holds for the whole run (the schedule of their own file aside).
    std::set<std::string> hold = names;
    if (file_schedule) {
      hold.clear();
      for (const CommandLineConfig::Given& g : given.values) hold.insert(g.name);
    }
    HoldThroughSchedule(hold, &run.config);
  }
  run.field_by_length = PinField(&run.config);
  run.poses_by_preset = !run.resumes && PosesByPreset(run.config);
  if (absl::Status s = CheckSegments(run.config); !s.ok()) return s;
  return run;
}

absl::StatusOr<bool> FitFieldToLog(const DriveLog& log, ResolvedRun* run) {
  if (!run->field_by_length || !log.lidars.empty()) return false;
  run->field_by_length = false;
  const Origin o = run->config.settings.origin("field");
  (void)run->config.settings.Set("field", std::string("static"), o, "field auto");
  run->config.notes.push_back(kCameraOnlyStaticNote);
  if (absl::Status s = CheckSegments(run->config); !s.ok()) return s;
  return true;
}

absl::StatusOr<bool> FitPosesToLog(const DriveLog& log, ResolvedRun* run) {
  if (!run->poses_by_preset || !PosesFromImages(log)) return false;
  run->poses_by_preset = false;
  const Origin o = run->config.settings.origin("pose-refinement");
  (void)run->config.settings.Set("pose-refinement", false, o, "poses from the log's images");
  for (ScheduleStage& stage : run->config.schedule) {
    for (const std::string& name : PoseSettings()) stage.set.erase(name);
  }
  run->config.notes.push_back(kImagePosesNote);
  if (absl::Status s = CheckSegments(run->config); !s.ok()) return s;
  return true;
}

}  // namespace streetsim::train::config
