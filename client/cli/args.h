// Minimal command-line flag parsing shared by the streetsim subcommands: --name value,
// --name=value and boolean --name. Unknown flags, missing values and repeated flags are errors.
#pragma once

#include <map>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"

namespace streetsim {

struct FlagSpec {
  std::string name;  // without the leading dashes
  bool takes_value = true;
  bool repeatable = false;  // e.g. --set: every occurrence is kept (ordered())
};

class ParsedArgs {
 public:
  static absl::StatusOr<ParsedArgs> Parse(const std::vector<std::string>& args,
                                          const std::vector<FlagSpec>& specs);
  std::optional<std::string> Get(const std::string& name) const;
  bool Has(const std::string& name) const { return values_.count(name) > 0; }
  absl::StatusOr<std::string> Required(const std::string& name) const;
  const std::vector<std::string>& positional() const { return positional_; }
  // Every flag as given, in command-line order (name, value; "" for a flag without one).
  const std::vector<std::pair<std::string, std::string>>& ordered() const { return ordered_; }

 private:
  std::map<std::string, std::string> values_;
  std::vector<std::string> positional_;
  std::vector<std::pair<std::string, std::string>> ordered_;
};

// Prints "streetsim <command>: <message>" as one line on stderr (newlines in the message become
// spaces) and returns exit_code: every subcommand reports failures this way.
int ReportFailure(const std::string& command, int exit_code, const absl::Status& status);

}  // namespace streetsim
