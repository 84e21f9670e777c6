// `streetsim train`'s flags and help, generated from the settings table
// (scene/train/config/train_settings.h): every setting is a flag `--NAME VALUE` (a bool:
// `--NAME` and `--no-NAME`), and `--set NAME=VALUE`, `--config FILE.json` and `--preset NAME`
// reach the same settings. `streetsim jobs train` takes the same flags.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client/cli/args.h"
#include "scene/train/config/run_resolution.h"

namespace streetsim {

// The setting flags (and --set, --config, --preset) for ParsedArgs.
std::vector<FlagSpec> TrainSettingFlagSpecs();

// The parsed flags' settings, preset and config file, in command-line order (a later value of a
// setting wins). InvalidArgument for a malformed --set.
absl::StatusOr<train::config::CommandLineConfig> TrainCommandLineConfig(const ParsedArgs& args);

// Help: the common settings (all: every setting), the presets and how a run resumes.
std::string TrainHelp(bool all);

}  // namespace streetsim
