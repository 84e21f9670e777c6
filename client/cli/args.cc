#include "client/cli/args.h"

#include <algorithm>
#include <cstdio>

#include "absl/strings/str_cat.h"

namespace streetsim {

absl::StatusOr<ParsedArgs> ParsedArgs::Parse(const std::vector<std::string>& args,
                                             const std::vector<FlagSpec>& specs) {
  ParsedArgs out;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a.rfind("--", 0) != 0 || a.size() == 2) {
      out.positional_.push_back(a);
      continue;
    }
    std::string name = a.substr(2), value;
    bool has_inline = false;
    if (const size_t eq = name.find('='); eq != std::string::npos) {
      value = name.substr(eq + 1);
      name = name.substr(0, eq);
      has_inline = true;
    }
    const FlagSpec* spec = nullptr;
    for (const FlagSpec& s : specs) {
      if (s.name == name) spec = &s;
    }
    if (spec == nullptr) return absl::InvalidArgumentError(absl::StrCat("unknown flag --", name));
    if (out.values_.count(name) && !spec->repeatable) {
      return absl::InvalidArgumentError(absl::StrCat("--", name, " given twice"));
    }
    if (spec->takes_value && !has_inline) {
      if (i + 1 >= args.size()) return absl::InvalidArgumentError(absl::StrCat("--", name, " needs a value"));
      value = args[++i];
    } else if (!spec->takes_value && has_inline) {
      return absl::InvalidArgumentError(absl::StrCat("--", name, " takes no value"));
    }
    out.values_[name] = value;
    out.ordered_.emplace_back(name, value);
  }
  return out;
}

std::optional<std::string> ParsedArgs::Get(const std::string& name) const {
  auto it = values_.find(name);
  if (it == values_.end()) return std::nullopt;
  return it->second;
}

absl::StatusOr<std::string> ParsedArgs::Required(const std::string& name) const {
  auto it = values_.find(name);
  if (it == values_.end() || it->second.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("--", name, " is required"));
  }
  return it->second;
}

int ReportFailure(const std::string& command, int exit_code, const absl::Status& status) {
  std::string msg(status.message());
  std::replace(msg.begin(), msg.end(), '\n', ' ');
  std::fprintf(stderr, "streetsim %s: %s\n", command.c_str(), msg.c_str());
  return exit_code;
}

}  // namespace streetsim
