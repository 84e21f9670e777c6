#include "client/cli/train_flags.h"

#include "absl/strings/str_cat.h"
#include "scene/train/config/run_config.h"
#include "scene/train/config/train_settings.h"

namespace streetsim {
namespace {

using train::config::SettingDef;
using train::config::SettingGroup;
using train::config::SettingType;

const SettingDef* FindDef(const std::string& name) {
  for (const SettingDef& d : train::config::TrainSettingDefs()) {
    if (name == d.name) return &d;
  }
  return nullptr;
}

std::string Wrap(const std::string& text, size_t indent, size_t width = 100) {
  std::string out, line;
  size_t b = 0;
  while (b < text.size()) {
    size_t e = text.find(' ', b);
    if (e == std::string::npos) e = text.size();
    const std::string word = text.substr(b, e - b);
    if (!line.empty() && indent + line.size() + 1 + word.size() > width) {
      out += std::string(indent, ' ') + line + "\n";
      line.clear();
    }
    line += (line.empty() ? "" : " ") + word;
    b = e + 1;
  }
  if (!line.empty()) out += std::string(indent, ' ') + line + "\n";
  return out;
}

}  // namespace

std::vector<FlagSpec> TrainSettingFlagSpecs() {
  std::vector<FlagSpec> specs = {{"set", true, true}, {"config"}, {"preset"}};
  for (const SettingDef& d : train::config::TrainSettingDefs()) {
    if (d.type == SettingType::kBool) {
      specs.push_back({d.name, false});
      specs.push_back({absl::StrCat("no-", d.name), false});
    } else {
      specs.push_back({d.name, true});
    }
  }
  return specs;
}

absl::StatusOr<train::config::CommandLineConfig> TrainCommandLineConfig(const ParsedArgs& args) {
  train::config::CommandLineConfig c;
  if (auto v = args.Get("preset")) c.preset = *v;
  if (auto v = args.Get("config")) c.config_path = *v;
  for (const auto& [flag, value] : args.ordered()) {
    if (flag == "set") {
      const size_t eq = value.find('=');
      if (eq == std::string::npos || eq == 0) {
        return absl::InvalidArgumentError(absl::StrCat("--set takes NAME=VALUE, not '", value, "'"));
      }
      c.values.push_back({value.substr(0, eq), value.substr(eq + 1), absl::StrCat("--set ", value.substr(0, eq))});
      continue;
    }
    if (const SettingDef* d = FindDef(flag)) {
      c.values.push_back({flag, d->type == SettingType::kBool ? "true" : value, absl::StrCat("--", flag)});
    } else if (flag.rfind("no-", 0) == 0 && FindDef(flag.substr(3)) != nullptr) {
      c.values.push_back({flag.substr(3), "false", absl::StrCat("--", flag)});
    }
  }
  return c;
}

std::string TrainHelp(bool all) {
  std::string out =
      "streetsim train --log PATH --out DIR [--preset NAME] [--config FILE.json] [--set NAME=VALUE]...\n"
      "                [--NAME VALUE]... [--resume] [--help-all]\n"
      "  Trains a scene from a driving log (docs/training.md). With no other flag it runs the default\n"
      "  preset, the measured best, in one command: its stages run in one process and checkpoint as\n"
      "  they go. Ctrl-C (or SIGTERM) stops with a checkpoint (exit 130 / 143); --resume goes on, also\n"
      "  after kill -9. The run's whole config is written to DIR/config.json at its start; --resume\n"
      "  reads it and applies only the settings given with it, from the checkpoint on.\n"
      "  Every setting is a flag --NAME VALUE (a bool: --NAME / --no-NAME) and --set NAME=VALUE.\n\npresets:\n";
  for (const std::string& p : train::config::PresetNames()) {
    out += absl::StrCat("  ", p, p == train::config::kDefaultPreset ? " (default)" : "", "\n");
    out += Wrap(train::config::PresetDescription(p), 6);
  }
  out += all ? "\nsettings:\n" : "\ncommon settings (--help-all: every setting):\n";
  // The default preset's value where it sets one (its last stage's, where a stage changes it).
  const absl::StatusOr<train::config::RunConfig> preset = train::config::PresetConfig(train::config::kDefaultPreset);
  const std::vector<train::config::Segment> segments =
      preset.ok() ? train::config::Segments(*preset) : std::vector<train::config::Segment>{};
  for (const SettingDef& d : train::config::TrainSettingDefs()) {
    if (!all && d.group != SettingGroup::kCommon) continue;
    std::string preset_value;
    if (!segments.empty()) {
      const train::config::Settings& last = segments.back().settings;
      if (last.Get(d.name) != d.default_value) {
        preset_value = absl::StrCat("; ", train::config::kDefaultPreset, ": ", train::config::FormatValue(last.Get(d.name)));
      }
    }
    out += absl::StrCat("  --", d.name, d.type == SettingType::kBool ? "" : " VALUE", "   (",
                        train::config::DescribeRange(d), "; default ", train::config::FormatValue(d.default_value),
                        preset_value, ")\n");
    out += Wrap(d.help, 6);
  }
  return out;
}

}  // namespace streetsim
