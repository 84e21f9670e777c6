#include "scene/train/config/run_config.h"

#include <algorithm>
#include <filesystem>
#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "scene/common/checked_file.h"
#include "scene/train/config/preset_files.h"
#include "scene/train/config/train_settings.h"

namespace streetsim::train::config {
namespace {

// A config file is small; anything past this is not one (and is not read into memory whole).
constexpr std::uintmax_t kMaxConfigBytes = 1 << 20;

absl::StatusOr<std::vector<ScheduleStage>> ParseSchedule(const nlohmann::json& j, const std::string& source) {
  if (!j.is_array()) return absl::InvalidArgumentError(absl::StrCat(source, ": schedule must be a list of stages"));
  if (j.size() > 1000) return absl::InvalidArgumentError(absl::StrCat(source, ": schedule has more than 1000 stages"));
  std::vector<ScheduleStage> out;
  Settings scratch = DefaultTrainSettings();
  for (size_t k = 0; k < j.size(); ++k) {
    const std::string where = absl::StrCat(source, ": schedule[", k, "]");
    const nlohmann::json& st = j[k];
    if (!st.is_object() || !st.contains("from") || !st["from"].is_number_integer() || st["from"].get<int64_t>() < 0) {
      return absl::InvalidArgumentError(absl::StrCat(where, " needs \"from\": an iteration >= 0"));
    }
    ScheduleStage stage;
    stage.from = st["from"].get<int64_t>();
    if (!out.empty() && stage.from <= out.back().from) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": stages must start at increasing iterations"));
    }
    for (const auto& [key, value] : st.items()) {
      if (key != "from" && key != "set" && key != "given") {
        return absl::InvalidArgumentError(absl::StrCat(where, ": unknown key '", key, "' (from, set, given)"));
      }
    }
    if (st.contains("set")) {
      if (!st["set"].is_object()) return absl::InvalidArgumentError(absl::StrCat(where, ": set must be an object"));
      for (const auto& [name, value] : st["set"].items()) {
        if (name == "iterations") {
          return absl::InvalidArgumentError(absl::StrCat(where, ": iterations is the run's end, not a stage's"));
        }
        if (absl::Status s = scratch.SetJson(name, value, Origin::kPreset, where); !s.ok()) return s;
        stage.set[name] = scratch.Get(name);
      }
    }
    if (st.contains("given") && st["given"].is_array()) {
      for (const nlohmann::json& g : st["given"]) {
        if (g.is_string() && stage.set.count(g.get<std::string>())) stage.given.insert(g.get<std::string>());
      }
    }
    out.push_back(std::move(stage));
  }
  if (!out.empty() && out.front().from != 0) out.insert(out.begin(), ScheduleStage{});
  return out;
}

nlohmann::json ScheduleJson(const std::vector<ScheduleStage>& schedule) {
  nlohmann::json out = nlohmann::json::array();
  for (const ScheduleStage& s : schedule) {
    nlohmann::json set = nlohmann::json::object();
    for (const auto& [name, value] : s.set) set[name] = ValueToJson(value);
    nlohmann::json stage = {{"from", s.from}, {"set", set}};
    if (!s.given.empty()) stage["given"] = s.given;
    out.push_back(stage);
  }
  return out;
}

// The settings in force in stage k (the base plus every stage's set up to k).
Settings StageSettings(const RunConfig& config, size_t k) {
  Settings s = config.settings;
  for (size_t i = 0; i <= k && i < config.schedule.size(); ++i) {
    const ScheduleStage& stage = config.schedule[i];
    for (const auto& [name, value] : stage.set) {
      // Checked when the schedule was read.
      (void)s.Set(name, value, stage.given.count(name) ? Origin::kGiven : s.origin(name), "schedule");
    }
  }
  return s;
}

absl::StatusOr<nlohmann::json> ParseJson(const std::string& text, const std::string& source) {
  nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) return absl::InvalidArgumentError(absl::StrCat(source, " is not valid JSON"));
  if (!j.is_object()) return absl::InvalidArgumentError(absl::StrCat(source, " must hold a JSON object"));
  return j;
}

absl::Status CheckSchema(const nlohmann::json& j, const std::string& source, bool required) {
  if (!j.contains("schema_version")) {
    return required ? absl::InvalidArgumentError(absl::StrCat(source, " has no schema_version")) : absl::OkStatus();
  }
  if (!j["schema_version"].is_number_integer()) {
    return absl::InvalidArgumentError(absl::StrCat(source, ": schema_version must be an integer"));
  }
  const int64_t v = j["schema_version"].get<int64_t>();
  if (v > kConfigSchemaVersion) {
    return absl::InvalidArgumentError(absl::StrCat(source, " has schema_version ", v, ", newer than this streetsim's ",
                                                   kConfigSchemaVersion, ": use the streetsim that wrote it"));
  }
  if (v < 1) return absl::InvalidArgumentError(absl::StrCat(source, ": schema_version ", v, " is not a version"));
  return absl::OkStatus();
}

}  // namespace

RunConfig::RunConfig() : settings(DefaultTrainSettings()) {}

std::vector<Segment> Segments(const RunConfig& config) {
  std::vector<Segment> out;
  if (config.schedule.empty()) {
    out.push_back({config.settings.GetInt("iterations"), config.settings});
    return out;
  }
  const int64_t iterations = StageSettings(config, config.schedule.size() - 1).GetInt("iterations");
  for (size_t k = 0; k < config.schedule.size(); ++k) {
    const int64_t next = k + 1 < config.schedule.size() ? config.schedule[k + 1].from : iterations;
    const int64_t end = std::min(next, iterations);
    if (end <= config.schedule[k].from) break;
    out.push_back({end, StageSettings(config, k)});
    if (end == iterations) break;
  }
  // The last segment always reaches the run's end, at the run's iterations.
  if (!out.empty()) (void)out.back().settings.Set("iterations", iterations, Origin::kGiven, "schedule");
  return out;
}

std::vector<std::string> PresetNames() {
  std::vector<std::string> names;
  for (const auto& [name, text] : PresetFiles()) names.push_back(name);
  return names;
}

std::string PresetDescription(const std::string& name) {
  for (const auto& [n, text] : PresetFiles()) {
    if (n != name) continue;
    nlohmann::json j = nlohmann::json::parse(text, nullptr, false);
    if (j.is_object() && j.contains("description") && j["description"].is_string()) return j["description"];
  }
  return "";
}

absl::StatusOr<RunConfig> PresetConfig(const std::string& name) {
  for (const auto& [n, text] : PresetFiles()) {
    if (n != name) continue;
    RunConfig config;
    config.preset = name;
    if (absl::Status s = ApplyConfigDocument(text, Origin::kPreset, absl::StrCat("preset ", name), &config); !s.ok()) {
      return absl::InternalError(s.message());  // the build's own file: a bug, not bad input
    }
    return config;
  }
  return absl::InvalidArgumentError(
      absl::StrCat("no preset '", name, "' (presets: ", absl::StrJoin(PresetNames(), ", "), ")"));
}

absl::Status ApplyConfigDocument(const std::string& text, Origin origin, const std::string& source,
                                 RunConfig* config) {
  absl::StatusOr<nlohmann::json> j = ParseJson(text, source);
  if (!j.ok()) return j.status();
  if (absl::Status s = CheckSchema(*j, source, /*required=*/false); !s.ok()) return s;
  for (const auto& [key, value] : j->items()) {
    if (key != "schema_version" && key != "description" && key != "settings" && key != "schedule") {
      return absl::InvalidArgumentError(
          absl::StrCat(source, ": unknown key '", key, "' (schema_version, description, settings, schedule)"));
    }
  }
  if (j->contains("settings")) {
    const nlohmann::json& s = (*j)["settings"];
    if (!s.is_object()) return absl::InvalidArgumentError(absl::StrCat(source, ": settings must be an object"));
    for (const auto& [name, value] : s.items()) {
      if (absl::Status st = config->settings.SetJson(name, value, origin, source); !st.ok()) return st;
    }
  }
  if (j->contains("schedule")) {
    absl::StatusOr<std::vector<ScheduleStage>> schedule = ParseSchedule((*j)["schedule"], source);
    if (!schedule.ok()) return schedule.status();
    config->schedule = std::move(*schedule);
  }
  return absl::OkStatus();
}

void HoldThroughSchedule(const std::set<std::string>& names, RunConfig* config) {
  for (ScheduleStage& stage : config->schedule) {
    for (const std::string& n : names) stage.set.erase(n);
  }
}

absl::StatusOr<std::vector<std::string>> ChangeFrom(int64_t iteration, const Settings& given,
                                                    const std::set<std::string>& given_names, RunConfig* config) {
  if (config->schedule.empty()) config->schedule.push_back(ScheduleStage{});
  size_t k = 0;
  while (k + 1 < config->schedule.size() && config->schedule[k + 1].from <= iteration) ++k;
  const Settings in_force = StageSettings(*config, k);
  std::map<std::string, SettingValue> changes;
  std::vector<std::string> changed;
  for (const std::string& name : given_names) {
    if (given.Get(name) == in_force.Get(name)) continue;
    if (name == "iterations") {  // the run's end: the run's own
      (void)config->settings.Set(name, given.Get(name), Origin::kGiven, "resume");
      changed.push_back(name);
      continue;
    }
    changes[name] = given.Get(name);
  }
  if (changes.empty()) return changed;
  if (config->schedule[k].from != iteration) {
    config->schedule.insert(config->schedule.begin() + static_cast<std::ptrdiff_t>(k) + 1,
                            ScheduleStage{iteration, {}});
    ++k;
  }
  for (const auto& [name, value] : changes) {
    config->schedule[k].set[name] = value;
    config->schedule[k].given.insert(name);
    changed.push_back(name);
    for (size_t i = k + 1; i < config->schedule.size(); ++i) config->schedule[i].set.erase(name);
  }
  return changed;
}

std::string RunConfigJson(const RunConfig& config) {
  nlohmann::ordered_json j;  // in this order for a reader: version, preset, settings, schedule
  j["schema_version"] = kConfigSchemaVersion;
  j["preset"] = config.preset;
  nlohmann::json given = nlohmann::json::array();
  for (const SettingDef& d : config.settings.defs()) {
    if (config.settings.given(d.name)) given.push_back(d.name);
  }
  j["given"] = given;
  j["settings"] = nlohmann::ordered_json::parse(config.settings.ToJson().dump());
  j["schedule"] = nlohmann::ordered_json::parse(ScheduleJson(config.schedule).dump());
  if (!config.notes.empty()) j["notes"] = config.notes;
  return j.dump(2) + "\n";
}

absl::Status WriteRunConfig(const std::string& dir, const RunConfig& config) {
  return checked_file::WriteAtomically((std::filesystem::path(dir) / kRunConfigFileName).string(),
                                       RunConfigJson(config));
}

absl::StatusOr<RunConfig> ReadRunConfig(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kRunConfigFileName).string();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return absl::NotFoundError(absl::StrCat(path, " does not exist"));
  absl::StatusOr<std::string> text = checked_file::ReadBounded(path, kMaxConfigBytes);
  if (!text.ok()) {
    const bool large = absl::IsOutOfRange(text.status());
    return absl::DataLossError(
        absl::StrCat(path, " is damaged (", large ? "larger than 1 MiB" : text.status().message(), ")"));
  }
  absl::StatusOr<nlohmann::json> j = ParseJson(*text, path);
  if (!j.ok()) return absl::DataLossError(absl::StrCat(j.status().message(), " (damaged)"));
  if (absl::Status s = CheckSchema(*j, path, /*required=*/true); !s.ok()) return s;
  RunConfig config;
  if (!j->contains("settings") || !(*j)["settings"].is_object()) {
    return absl::DataLossError(absl::StrCat(path, " has no settings (damaged)"));
  }
  std::set<std::string> given;
  if (j->contains("given") && (*j)["given"].is_array()) {
    for (const nlohmann::json& g : (*j)["given"]) {
      if (g.is_string()) given.insert(g.get<std::string>());
    }
  }
  for (const auto& [name, value] : (*j)["settings"].items()) {
    const Origin origin = given.count(name) ? Origin::kGiven : Origin::kPreset;
    if (absl::Status s = config.settings.SetJson(name, value, origin, path); !s.ok()) return s;
  }
  if (j->contains("preset") && (*j)["preset"].is_string()) config.preset = (*j)["preset"];
  if (j->contains("notes") && (*j)["notes"].is_array()) {
    for (const nlohmann::json& n : (*j)["notes"]) {
      if (n.is_string()) config.notes.push_back(n.get<std::string>());
    }
  }
  if (j->contains("schedule")) {
    absl::StatusOr<std::vector<ScheduleStage>> schedule = ParseSchedule((*j)["schedule"], path);
    if (!schedule.ok()) return schedule.status();
    config.schedule = std::move(*schedule);
  }
  return config;
}

}  // namespace streetsim::train::config
