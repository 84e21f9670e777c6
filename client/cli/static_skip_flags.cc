#include "client/cli/static_skip_flags.h"

#include <cmath>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace streetsim {
namespace {

// Above this a threshold is a typo, not a setting (the log's whole extent is rarely 1 km).
constexpr double kMaxThreshold = 1000;

absl::Status ReadThreshold(const ParsedArgs& args, const std::string& flag, double* out) {
  std::optional<std::string> v = args.Get(flag);
  if (!v) return absl::OkStatus();
  double x = 0;
  if (!absl::SimpleAtod(*v, &x) || !std::isfinite(x) || x < 0 || x > kMaxThreshold) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", flag, " must be a number in [0, ", kMaxThreshold, "], got '", *v, "'"));
  }
  *out = x;
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<field::StaticSkipOptions> StaticSkipFromFlags(const ParsedArgs& args) {
  field::StaticSkipOptions o;
  if (absl::Status s = ReadThreshold(args, "static-motion-m", &o.motion_threshold_m); !s.ok()) return s;
  if (absl::Status s = ReadThreshold(args, "static-sh", &o.sh_threshold); !s.ok()) return s;
  return o;
}

absl::StatusOr<bool> ExactFieldFromFlags(const ParsedArgs& args) {
  const std::string v = args.Get("field-serving").value_or("served");
  if (v != "served" && v != "exact") {
    return absl::InvalidArgumentError(absl::StrCat("--field-serving takes served or exact, got '", v, "'"));
  }
  return v == "exact";
}

}  // namespace streetsim
