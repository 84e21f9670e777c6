// Bearer-token authentication, checked at the top of every streetsim handler (gRPC's
// AuthMetadataProcessor only runs on secure channels, and the token must also work on loopback
// without TLS). Health and reflection stay open so that probes work.
#pragma once

#include <string>

#include <grpcpp/server_context.h>

#include "absl/status/statusor.h"

namespace streetsim::server {

class Authenticator {
 public:
  Authenticator() = default;  // no token: every call allowed
  explicit Authenticator(std::string token) : token_(std::move(token)) {}
  // Reads the token (first line, surrounding whitespace trimmed; must be non-empty).
  static absl::StatusOr<Authenticator> FromFile(const std::string& path);

  bool enabled() const { return !token_.empty(); }
  // UNAUTHENTICATED unless metadata "authorization: Bearer <token>" matches.
  absl::Status Check(const grpc::ServerContextBase& ctx) const;

 private:
  std::string token_;
};

}  // namespace streetsim::server
