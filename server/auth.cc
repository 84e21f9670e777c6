#include "server/auth.h"

#include <fstream>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"

namespace streetsim::server {

absl::StatusOr<Authenticator> Authenticator::FromFile(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::InvalidArgumentError(absl::StrCat("--auth-token-file ", path, ": cannot open"));
  std::string line;
  std::getline(in, line);
  std::string token(absl::StripAsciiWhitespace(line));
  if (token.empty()) return absl::InvalidArgumentError(absl::StrCat("--auth-token-file ", path, ": empty token"));
  return Authenticator(token);
}

absl::Status Authenticator::Check(const grpc::ServerContextBase& ctx) const {
  if (token_.empty()) return absl::OkStatus();
  const auto& md = ctx.client_metadata();
  auto it = md.find("authorization");
  if (it == md.end()) return absl::UnauthenticatedError("missing authorization: Bearer <token> metadata");
  const std::string value(it->second.data(), it->second.size());
  const std::string expected = "Bearer " + token_;
  // Constant time in the token's content.
  unsigned diff = value.size() != expected.size();
  for (size_t i = 0; i < expected.size(); ++i) {
    diff |= static_cast<unsigned char>(expected[i]) ^
            static_cast<unsigned char>(i < value.size() ? value[i] : 0);
  }
  if (diff) return absl::UnauthenticatedError("invalid bearer token");
  return absl::OkStatus();
}

}  // namespace streetsim::server
