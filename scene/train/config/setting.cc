#include "scene/train/config/setting.h"

#include <cmath>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace streetsim::train::config {
namespace {

// Integers past 2^53 do not survive a JSON double; no setting needs them.
constexpr double kMaxExactInt = 9007199254740992.0;

// A name or value from outside, safe to print: printable ASCII, at most 64 characters.
std::string Shown(const std::string& text) {
  std::string out;
  for (char c : text.substr(0, 64)) out += (c >= 0x20 && c < 0x7f) ? c : '?';
  return text.size() > 64 ? out + "..." : out;
}

absl::Status Refuse(const std::string& what, const SettingDef& def, const std::string& shown) {
  return absl::InvalidArgumentError(absl::StrCat(what, ": ", def.name, " must be ", DescribeRange(def), ", not ",
                                                 shown));
}

}  // namespace

std::string DescribeRange(const SettingDef& def) {
  auto num = [](double v) {
    if (v == std::floor(v) && std::fabs(v) < 1e16) return absl::StrCat(static_cast<int64_t>(v));
    return absl::StrCat(v);
  };
  switch (def.type) {
    case SettingType::kBool: return "true or false";
    case SettingType::kInt: return absl::StrCat("an integer in ", num(def.min), "..", num(def.max));
    case SettingType::kDouble:
      return absl::StrCat("a number in ", def.min_exclusive ? "(" : "[", num(def.min), ", ", num(def.max), "]");
    case SettingType::kChoice: return absl::StrCat("one of ", absl::StrJoin(def.choices, ", "));
    case SettingType::kText: return "text";
  }
  return "?";
}

std::string FormatValue(const SettingValue& value) {
  if (const bool* b = std::get_if<bool>(&value)) return *b ? "true" : "false";
  if (const int64_t* i = std::get_if<int64_t>(&value)) return absl::StrCat(*i);
  if (const double* d = std::get_if<double>(&value)) return absl::StrCat(*d);
  return std::get<std::string>(value);
}

nlohmann::json ValueToJson(const SettingValue& value) {
  return std::visit([](const auto& v) { return nlohmann::json(v); }, value);
}

Settings::Settings(const std::vector<SettingDef>* defs) : defs_(defs) {
  for (const SettingDef& d : *defs_) {
    values_[d.name] = d.default_value;
    origins_[d.name] = Origin::kDefault;
  }
}

const SettingDef* Settings::Find(const std::string& name) const {
  for (const SettingDef& d : *defs_) {
    if (name == d.name) return &d;
  }
  return nullptr;
}

const SettingValue& Settings::Get(const std::string& name) const { return values_.at(name); }

Origin Settings::origin(const std::string& name) const { return origins_.at(name); }

absl::Status Settings::Set(const std::string& name, const SettingValue& value, Origin origin,
                           const std::string& what) {
  const SettingDef* def = Find(name);
  if (def == nullptr) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, ": unknown setting '", Shown(name), "' (`streetsim train --help-all` lists them)"));
  }
  const std::string shown = absl::StrCat("'", Shown(FormatValue(value)), "'");
  switch (def->type) {
    case SettingType::kBool:
      if (!std::holds_alternative<bool>(value)) return Refuse(what, *def, shown);
      break;
    case SettingType::kInt: {
      const int64_t* i = std::get_if<int64_t>(&value);
      if (i == nullptr || *i < def->min || *i > def->max) return Refuse(what, *def, shown);
      break;
    }
    case SettingType::kDouble: {
      double v = 0;
      if (const double* d = std::get_if<double>(&value)) {
        v = *d;
      } else if (const int64_t* i = std::get_if<int64_t>(&value)) {
        v = static_cast<double>(*i);
      } else {
        return Refuse(what, *def, shown);
      }
      if (!std::isfinite(v) || v > def->max || v < def->min || (def->min_exclusive && v == def->min)) {
        return Refuse(what, *def, shown);
      }
      values_[name] = v;
      origins_[name] = origin;
      return absl::OkStatus();
    }
    case SettingType::kChoice: {
      const std::string* s = std::get_if<std::string>(&value);
      bool known = false;
      for (const std::string& c : def->choices) known = known || (s != nullptr && *s == c);
      if (!known) return Refuse(what, *def, shown);
      break;
    }
    case SettingType::kText: {
      const std::string* s = std::get_if<std::string>(&value);
      if (s == nullptr) return Refuse(what, *def, shown);
      if (def->check_text != nullptr) {
        if (absl::Status st = def->check_text(*s); !st.ok()) {
          return absl::InvalidArgumentError(absl::StrCat(what, ": ", def->name, ": ", st.message()));
        }
      }
      break;
    }
  }
  values_[name] = value;
  origins_[name] = origin;
  return absl::OkStatus();
}

absl::Status Settings::SetText(const std::string& name, const std::string& text, Origin origin,
                               const std::string& what) {
  const SettingDef* def = Find(name);
  if (def == nullptr) return Set(name, SettingValue(text), origin, what);  // the unknown-name message
  switch (def->type) {
    case SettingType::kBool:
      if (text == "true" || text == "1") return Set(name, true, origin, what);
      if (text == "false" || text == "0") return Set(name, false, origin, what);
      return Refuse(what, *def, absl::StrCat("'", Shown(text), "'"));
    case SettingType::kInt: {
      int64_t v = 0;
      if (!absl::SimpleAtoi(text, &v)) return Refuse(what, *def, absl::StrCat("'", Shown(text), "'"));
      return Set(name, v, origin, what);
    }
    case SettingType::kDouble: {
      double v = 0;
      if (!absl::SimpleAtod(text, &v)) return Refuse(what, *def, absl::StrCat("'", Shown(text), "'"));
      return Set(name, v, origin, what);
    }
    case SettingType::kChoice:
    case SettingType::kText: return Set(name, text, origin, what);
  }
  return absl::OkStatus();
}

absl::Status Settings::SetJson(const std::string& name, const nlohmann::json& value, Origin origin,
                               const std::string& what) {
  const SettingDef* def = Find(name);
  if (def == nullptr) return Set(name, SettingValue(std::string()), origin, what);
  const std::string shown = Shown(value.dump());
  switch (def->type) {
    case SettingType::kBool:
      if (!value.is_boolean()) return Refuse(what, *def, shown);
      return Set(name, value.get<bool>(), origin, what);
    case SettingType::kInt: {
      if (!value.is_number()) return Refuse(what, *def, shown);
      const double d = value.get<double>();
      if (d != std::floor(d) || std::fabs(d) > kMaxExactInt) return Refuse(what, *def, shown);
      return Set(name, value.is_number_unsigned() ? static_cast<int64_t>(value.get<uint64_t>())
                                                  : value.get<int64_t>(),
                 origin, what);
    }
    case SettingType::kDouble:
      if (!value.is_number()) return Refuse(what, *def, shown);
      return Set(name, value.get<double>(), origin, what);
    case SettingType::kChoice:
    case SettingType::kText:
      if (!value.is_string()) return Refuse(what, *def, shown);
      return Set(name, value.get<std::string>(), origin, what);
  }
  return absl::OkStatus();
}

nlohmann::json Settings::ToJson() const {
  nlohmann::json out = nlohmann::json::object();
  for (const SettingDef& d : *defs_) out[d.name] = ValueToJson(values_.at(d.name));
  return out;
}

}  // namespace streetsim::train::config
