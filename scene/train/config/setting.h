// One training setting's declaration and a set of resolved values (docs/training.md "Settings").
// A setting is declared once, in the table of train_settings.cc: its name (the flag `--NAME`, the
// key in config files and `--set NAME=VALUE`), type, default, range, help and group. Everything
// that reads or checks a value goes through the declaration, so a flag, a config file, a training
// job and a resumed run's config.json all refuse the same values with the same message.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <variant>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include <nlohmann/json_fwd.hpp>

namespace streetsim::train::config {

enum class SettingType { kBool, kInt, kDouble, kChoice, kText };
enum class SettingGroup { kCommon, kAdvanced };

using SettingValue = std::variant<bool, int64_t, double, std::string>;

struct TrainRunOptions;  // train_settings.h

struct SettingDef {
  const char* name = "";
  SettingType type = SettingType::kInt;
  SettingValue default_value;
  // kInt / kDouble: the inclusive range; min_exclusive makes the low end open ((0, 1]).
  double min = 0, max = 0;
  bool min_exclusive = false;
  std::vector<std::string> choices = {};  // kChoice
  // kText: a check of its own (e.g. the extended field's module list); nullptr: any text.
  absl::Status (*check_text)(const std::string& text) = nullptr;
  SettingGroup group = SettingGroup::kAdvanced;
  const char* help = "";
  // Writes the value into the trainer's options (TrainRunOptions, train_settings.h).
  void (*apply)(const SettingValue& value, TrainRunOptions* options) = nullptr;
};

// Where a value came from: relations between settings ("needs a field") are checked for the
// values a user gave, not for a preset's (a preset's motion prior is not an error in a run that
// turns out static).
enum class Origin { kDefault, kPreset, kGiven };

// The declared settings' values; every declared setting has one (its default until set).
class Settings {
 public:
  explicit Settings(const std::vector<SettingDef>* defs);

  const std::vector<SettingDef>& defs() const { return *defs_; }
  // nullptr when no setting has that name.
  const SettingDef* Find(const std::string& name) const;

  // InvalidArgument naming the setting (`what` says where it came from: "--iterations",
  // "--set iterations", "config.json") for an unknown name, a wrong type or a value out of range.
  absl::Status Set(const std::string& name, const SettingValue& value, Origin origin, const std::string& what);
  // The same from text (a flag's or `--set`'s value; "true"/"false" for a bool).
  absl::Status SetText(const std::string& name, const std::string& text, Origin origin, const std::string& what);
  // The same from a JSON value (a config file's).
  absl::Status SetJson(const std::string& name, const nlohmann::json& value, Origin origin, const std::string& what);

  const SettingValue& Get(const std::string& name) const;
  bool GetBool(const std::string& name) const { return std::get<bool>(Get(name)); }
  int64_t GetInt(const std::string& name) const { return std::get<int64_t>(Get(name)); }
  double GetDouble(const std::string& name) const { return std::get<double>(Get(name)); }
  const std::string& GetText(const std::string& name) const { return std::get<std::string>(Get(name)); }
  Origin origin(const std::string& name) const;
  bool given(const std::string& name) const { return origin(name) == Origin::kGiven; }

  // Every setting's value, by name.
  nlohmann::json ToJson() const;
  const std::map<std::string, SettingValue>& values() const { return values_; }

 private:
  const std::vector<SettingDef>* defs_;
  std::map<std::string, SettingValue> values_;
  std::map<std::string, Origin> origins_;
};

// A value as a flag or `--set` writes it ("true", "12510", "0.3", "quality").
std::string FormatValue(const SettingValue& value);
// A value as JSON (bool, integer, number or string).
nlohmann::json ValueToJson(const SettingValue& value);
// The declaration's range or choices, for messages and help ("an integer in 1..10000000").
std::string DescribeRange(const SettingDef& def);

}  // namespace streetsim::train::config
