// absl::Status inside, canonical gRPC status codes at the edge: the one mapping.
#pragma once

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace streetsim::server {

grpc::Status ToGrpcStatus(const absl::Status& status);

}  // namespace streetsim::server
