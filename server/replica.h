// Replicas (docs/deploy.md): servers that share one state dir each name themselves
// (`streetsim serve --replica NAME`, or STREETSIM_REPLICA: a Kubernetes StatefulSet pod's name).
// The ids a replica creates (sessions, jobs) start with "NAME." so that a client library can send
// a session's or a job's calls to the replica that holds it, and a replica adopts at restart only
// the jobs that are its own.
#pragma once

#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace streetsim::server {

// A replica name is a DNS label: 1..63 of [a-z0-9-], starting and ending alphanumeric.
absl::Status ValidateReplicaName(std::string_view name);

// "NAME.<local>" for a named replica, "<local>" otherwise.
std::string ReplicaScopedId(const std::string& replica, const std::string& local_id);

// The replica an id names ("" for an id without one).
std::string_view ReplicaOfId(std::string_view id);

}  // namespace streetsim::server
