// What makes two requests "the same request" for request_id idempotency: every field but the
// request_id itself. A request_id reused for a different request is an error, not a silent return
// of the earlier object (the client would act on something it did not ask for).
#pragma once

#include <string>

#include <google/protobuf/message.h>

#include "absl/status/status.h"

namespace streetsim::server {

// Deterministic bytes of `message` (maps in key order), for comparing requests.
std::string Fingerprint(const google::protobuf::Message& message);

// The request's fingerprint without its request_id.
template <typename Request>
std::string RequestFingerprint(const Request& request) {
  Request copy = request;
  copy.clear_request_id();
  return Fingerprint(copy);
}

// INVALID_ARGUMENT: request_id (shortened) was used before for a different `what`.
absl::Status RequestIdReused(const std::string& request_id, const std::string& what);

}  // namespace streetsim::server
