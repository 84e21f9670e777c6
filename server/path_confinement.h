// Confining client-supplied paths to a root directory: the real path (symlinks and ".."
// resolved) must lie inside the real path of the root.
#pragma once

#include <string>

#include "absl/status/statusor.h"

namespace streetsim::server {

// `relative` is relative to `root` (absolute paths are refused). The target must exist.
// INVALID_ARGUMENT for absolute, empty or escaping paths (".." or a symlink out of the root);
// NOT_FOUND if it does not exist.
absl::StatusOr<std::string> ResolveUnderRoot(const std::string& root, const std::string& relative);

// True if `path` (already canonical) is `root` or inside it (both canonical).
bool IsInside(const std::string& root, const std::string& path);

}  // namespace streetsim::server
