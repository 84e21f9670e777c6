#include "server/replica.h"

#include "absl/strings/str_cat.h"
#include "server/echo.h"

namespace streetsim::server {

absl::Status ValidateReplicaName(std::string_view name) {
  const auto alnum = [](char c) { return (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9'); };
  bool ok = !name.empty() && name.size() <= 63 && alnum(name.front()) && alnum(name.back());
  for (char c : name) ok = ok && (alnum(c) || c == '-');
  if (!ok) {
    return absl::InvalidArgumentError(absl::StrCat("replica name ", Echo(std::string(name)),
                                                   ": 1-63 characters of a-z, 0-9 and '-', alphanumeric at both ends"));
  }
  return absl::OkStatus();
}

std::string ReplicaScopedId(const std::string& replica, const std::string& local_id) {
  return replica.empty() ? local_id : absl::StrCat(replica, ".", local_id);
}

std::string_view ReplicaOfId(std::string_view id) {
  const size_t dot = id.find('.');
  return dot == std::string_view::npos ? std::string_view() : id.substr(0, dot);
}

}  // namespace streetsim::server
