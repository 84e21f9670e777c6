// Untrusted strings (names, ids, paths from requests) as they may appear in an error message:
// quoted, at most kMaxEchoBytes of them, non-printable bytes escaped. A client that sends a
// megabyte name gets a short NOT_FOUND back, not a response too large for its metadata limit.
#pragma once

#include <cstddef>
#include <string>
#include "absl/strings/string_view.h"

namespace streetsim::server {

inline constexpr size_t kMaxEchoBytes = 96;

// 'value' shortened: 'first 96 bytes...' (N bytes)
std::string Echo(absl::string_view value);

}  // namespace streetsim::server
