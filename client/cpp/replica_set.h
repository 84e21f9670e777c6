// Replicas of one streetsim deployment from C++ (docs/server.md "Replicas"): the C++ counterpart of
// the Python ReplicaClient. Stateless calls go to the replicas in turn and fail over to the next
// on UNAVAILABLE; a session's or a job's calls go to the replica its id names ("NAME.s-...").
#pragma once

#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "client/cpp/streetsim_client.h"

namespace streetsim::client {

// The replica an id names ("" for an id without one).
std::string_view ReplicaOfId(std::string_view id);

class ReplicaSet {
 public:
  // `addresses`: replica name -> "host:port"; `options.target` is ignored. INVALID_ARGUMENT when
  // empty.
  static absl::StatusOr<std::unique_ptr<ReplicaSet>> Connect(const std::map<std::string, std::string>& addresses,
                                                              const ClientOptions& options);
  // Names with an address template such as "{replica}.streetsim-pods.default.svc:50051".
  static absl::StatusOr<std::unique_ptr<ReplicaSet>> Connect(const std::vector<std::string>& names,
                                                              const std::string& address_template,
                                                              const ClientOptions& options);

  // The client of a named replica (NOT_FOUND for a name this set does not have).
  absl::StatusOr<Client*> Replica(std::string_view name);
  // The client of the replica an id names (a session's or a job's); ids without one: the first.
  absl::StatusOr<Client*> Owner(std::string_view id);

  // Runs `call` on the next replica in turn, then on the others while they answer UNAVAILABLE.
  template <typename T>
  absl::StatusOr<T> Any(const std::function<absl::StatusOr<T>(Client&)>& call) {
    absl::Status last = absl::UnavailableError("no replica");
    for (Client* c : Rotation()) {
      absl::StatusOr<T> r = call(*c);
      if (r.ok() || !absl::IsUnavailable(r.status())) return r;
      last = r.status();
    }
    return last;
  }

  // The usual calls, routed.
  absl::StatusOr<v1::RenderResponse> Render(const v1::RenderRequest& request);
  absl::StatusOr<v1::Session> CreateSession(const v1::CreateSessionRequest& request);
  absl::StatusOr<v1::StepResponse> Step(const v1::StepRequest& request, double timeout_s = -1);
  absl::Status CloseSession(const std::string& id);
  absl::StatusOr<v1::Job> CreateTrainingJob(const v1::CreateTrainingJobRequest& request);
  absl::StatusOr<v1::Job> GetJob(const std::string& id);
  absl::StatusOr<v1::Job> CancelJob(const std::string& id);

  std::vector<std::string> names() const;

 private:
  std::vector<Client*> Rotation();  // every replica, starting with the next in turn

  std::map<std::string, std::unique_ptr<Client>, std::less<>> clients_;
  std::mutex mu_;
  size_t turn_ = 0;
};

}  // namespace streetsim::client
