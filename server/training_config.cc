#include "server/training_config.h"

#include <charconv>
#include <regex>

#include "absl/strings/str_cat.h"
#include "scene/train/config/run_resolution.h"
#include "scene/train/config/train_settings.h"
#include "server/echo.h"

namespace streetsim::server {
namespace {

constexpr int kMaxIterations = 10'000'000;  // `streetsim train --iterations`' own bound
constexpr int kMaxSettings = 256;           // more than the table has: not a config

absl::Status Bad(const std::string& message) {
  return absl::InvalidArgumentError(absl::StrCat("config.", message));
}

// The shortest text that parses back to exactly v (absl::StrCat keeps 6 digits: the trainer would
// get another scale than the job asked for).
std::string Number(double v) {
  char buf[32];
  const std::to_chars_result r = std::to_chars(buf, buf + sizeof(buf), v);
  return std::string(buf, r.ptr);
}

// The deprecated fields as settings (zero / unset: not given), each named by its field.
std::vector<train::config::CommandLineConfig::Given> LegacySettings(const v1::TrainingConfig& c) {
  std::vector<train::config::CommandLineConfig::Given> g;
  auto add = [&](const char* field, const char* setting, const std::string& value) {
    g.push_back({setting, value, absl::StrCat("config.", field)});
  };
  if (c.max_iterations() > 0) add("max_iterations", "iterations", std::to_string(c.max_iterations()));
  if (c.seed() != 0) add("seed", "seed", std::to_string(c.seed()));
  if (!c.field().empty()) add("field", "field", c.field());
  if (!c.field_modules().empty()) add("field_modules", "field-modules", c.field_modules());
  if (c.has_static_iterations()) add("static_iterations", "static-iterations", std::to_string(c.static_iterations()));
  if (c.resolution_scale() != 0) add("resolution_scale", "resolution-scale", Number(c.resolution_scale()));
  if (c.low_res_scale() != 0) add("low_res_scale", "low-res-scale", Number(c.low_res_scale()));
  if (c.low_res_iterations() != 0) {
    add("low_res_iterations", "low-res-iterations", std::to_string(c.low_res_iterations()));
  }
  if (c.has_holdout_every()) add("holdout_every", "holdout-every", std::to_string(c.holdout_every()));
  if (c.clip_frames() != 0) add("clip_frames", "clip-frames", std::to_string(c.clip_frames()));
  if (c.has_clip_overlap()) add("clip_overlap", "clip-overlap", std::to_string(c.clip_overlap()));
  if (c.field_lr_scale() != 0) add("field_lr_scale", "field-lr-scale", Number(c.field_lr_scale()));
  if (c.field_lr_decay_iterations() != 0) {
    add("field_lr_decay_iterations", "field-lr-decay-iterations", std::to_string(c.field_lr_decay_iterations()));
  }
  if (c.position_lr_decay_iterations() != 0) {
    add("position_lr_decay_iterations", "position-lr-decay-iterations",
        std::to_string(c.position_lr_decay_iterations()));
  }
  if (c.has_densify_until()) add("densify_until", "densify-until", std::to_string(c.densify_until()));
  if (c.field_ext_lr_scale() != 0) add("field_ext_lr_scale", "field-ext-lr-scale", Number(c.field_ext_lr_scale()));
  if (c.field_ext_lr_decay_iterations() != 0) {
    add("field_ext_lr_decay_iterations", "field-ext-lr-decay-iterations",
        std::to_string(c.field_ext_lr_decay_iterations()));
  }
  if (c.has_field_motion_prior()) add("field_motion_prior", "field-motion-prior", Number(c.field_motion_prior()));
  if (!c.field_motion_prior_scans().empty()) {
    add("field_motion_prior_scans", "field-motion-prior-scans", c.field_motion_prior_scans());
  }
  if (!c.backend().empty()) add("backend", "backend", c.backend());
  if (c.pose_refinement()) add("pose_refinement", "pose-refinement", "true");
  if (c.pose_lr_scale() != 0) add("pose_lr_scale", "pose-lr-scale", Number(c.pose_lr_scale()));
  return g;
}

// Every setting the config gives, the deprecated fields' first; the map's in name order (a
// proto map has none of its own), each named `config.settings[NAME]` in messages.
train::config::CommandLineConfig AsCommandLine(const v1::TrainingConfig& c) {
  train::config::CommandLineConfig cl;
  if (!c.preset().empty()) cl.preset = c.preset();
  cl.values = LegacySettings(c);
  std::map<std::string, std::string> sorted(c.settings().begin(), c.settings().end());
  for (const auto& [name, value] : sorted) {
    cl.values.push_back({name, value, absl::StrCat("config.settings[", Echo(name), "]")});
  }
  return cl;
}

}  // namespace

bool IsSceneName(const std::string& name) {
  static const std::regex kName("[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}");
  return std::regex_match(name, kName);
}

bool AsksTraining(const v1::TrainingConfig& c) {
  return c.max_iterations() > 0 || !c.preset().empty() || !c.settings().empty();
}

absl::Status ValidateTrainingConfig(const v1::TrainingConfig& c) {
  if (c.max_iterations() < 0 || c.max_iterations() > kMaxIterations) {
    return Bad(absl::StrCat("max_iterations must be in 0..", kMaxIterations));
  }
  if (c.settings_size() > kMaxSettings) return Bad(absl::StrCat("settings: more than ", kMaxSettings, " entries"));
  const train::config::CommandLineConfig cl = AsCommandLine(c);
  if (!AsksTraining(c)) {
    if (!cl.values.empty() || !c.continue_from_scene().empty()) {
      return Bad("training options need max_iterations > 0, a preset or settings (none of them: init only)");
    }
    return absl::OkStatus();
  }
  if (!c.continue_from_scene().empty()) {
    if (!IsSceneName(c.continue_from_scene())) {
      return Bad("continue_from_scene: 1-64 of [A-Za-z0-9_.-], not starting with '.'");
    }
    if (!c.preset().empty()) {
      return Bad("preset: a continuation keeps its scene's config (change settings instead)");
    }
    // The scene's own config decides the rest when the trainer resumes it: each value is checked
    // here on its own.
    train::config::Settings scratch = train::config::DefaultTrainSettings();
    for (const auto& g : cl.values) {
      if (absl::Status s = scratch.SetText(g.name, g.text, train::config::Origin::kGiven, g.what); !s.ok()) return s;
    }
    return absl::OkStatus();
  }
  // A new run resolves without its directory: exactly the trainer's checks.
  return train::config::ResolveRun("", /*resume=*/false, cl).status();
}

std::vector<std::string> TrainFlags(const v1::TrainingConfig& c) {
  const train::config::CommandLineConfig cl = AsCommandLine(c);
  std::vector<std::string> f;
  if (cl.preset) f.insert(f.end(), {"--preset", *cl.preset});
  for (const auto& g : cl.values) f.insert(f.end(), {"--set", absl::StrCat(g.name, "=", g.text)});
  return f;
}

}  // namespace streetsim::server
