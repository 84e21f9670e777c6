// --static-motion-m M, --static-sh S and --field-serving served|exact, shared by `streetsim serve`
// and `streetsim eval --served`: the static skip's thresholds (scene/field/static_skip.h; defaults 0.01 m and 0.01; 0 makes every
// Gaussian dynamic, i.e. no skip). Bad values (not a number, negative, NaN, above 1000) are
// InvalidArgument naming the flag.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "client/cli/args.h"
#include "scene/field/static_skip.h"

namespace streetsim {

inline const std::vector<FlagSpec>& StaticSkipFlags() {
  static const std::vector<FlagSpec> kFlags = {{"static-motion-m"}, {"static-sh"}, {"field-serving"}};
  return kFlags;
}

absl::StatusOr<field::StaticSkipOptions> StaticSkipFromFlags(const ParsedArgs& args);

// --field-serving served|exact (default served): a dynamic scene through its serving form
// (scene/field/serving_form.h) or through the field's network per timestamp. Returns whether exact.
absl::StatusOr<bool> ExactFieldFromFlags(const ParsedArgs& args);

}  // namespace streetsim
