#include "server/path_confinement.h"

#include <limits.h>
#include <stdlib.h>

#include <cerrno>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "server/echo.h"

namespace streetsim::server {
namespace {

absl::StatusOr<std::string> RealPath(const std::string& path) {
  char buf[PATH_MAX];
  if (::realpath(path.c_str(), buf) == nullptr) {
    if (errno == ENOENT || errno == ENOTDIR) {
      return absl::NotFoundError(absl::StrCat(path, ": no such file or directory"));
    }
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", std::strerror(errno)));
  }
  return std::string(buf);
}

}  // namespace

bool IsInside(const std::string& root, const std::string& path) {
  if (path == root) return true;
  const std::string prefix = root.back() == '/' ? root : root + "/";
  return path.compare(0, prefix.size(), prefix) == 0;
}

absl::StatusOr<std::string> ResolveUnderRoot(const std::string& root, const std::string& relative) {
  if (relative.empty()) return absl::InvalidArgumentError("empty path");
  if (relative[0] == '/') {
    return absl::InvalidArgumentError(
        absl::StrCat("path ", Echo(relative), " must be relative to the server's data root"));
  }
  if (relative.find('\0') != std::string::npos) return absl::InvalidArgumentError("NUL in path");
  absl::StatusOr<std::string> real_root = RealPath(root);
  if (!real_root.ok()) return absl::FailedPreconditionError("the server's data root is missing");
  // Refuse ".." components outright (even ones that would stay inside).
  size_t start = 0;
  while (start <= relative.size()) {
    size_t end = relative.find('/', start);
    if (end == std::string::npos) end = relative.size();
    if (relative.compare(start, end - start, "..") == 0 && end - start == 2) {
      return absl::InvalidArgumentError(
          absl::StrCat("path ", Echo(relative), " leaves the server's data root"));
    }
    start = end + 1;
  }
  absl::StatusOr<std::string> real = RealPath(*real_root + "/" + relative);
  if (!real.ok()) {
    if (absl::IsNotFound(real.status())) {
      return absl::NotFoundError(absl::StrCat(Echo(relative), " not found under the data root"));
    }
    return real.status();
  }
  if (!IsInside(*real_root, *real)) {
    return absl::InvalidArgumentError(
        absl::StrCat("path ", Echo(relative), " leaves the server's data root"));
  }
  return *real;
}

}  // namespace streetsim::server
