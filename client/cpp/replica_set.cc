#include "client/cpp/replica_set.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"

namespace streetsim::client {

std::string_view ReplicaOfId(std::string_view id) {
  const size_t dot = id.find('.');
  return dot == std::string_view::npos ? std::string_view() : id.substr(0, dot);
}

absl::StatusOr<std::unique_ptr<ReplicaSet>> ReplicaSet::Connect(const std::map<std::string, std::string>& addresses,
                                                                const ClientOptions& options) {
  if (addresses.empty()) return absl::InvalidArgumentError("ReplicaSet: no replicas");
  auto set = std::unique_ptr<ReplicaSet>(new ReplicaSet());
  for (const auto& [name, address] : addresses) {
    ClientOptions o = options;
    o.target = address;
    absl::StatusOr<std::unique_ptr<Client>> c = Client::Connect(o);
    if (!c.ok()) return c.status();
    set->clients_[name] = *std::move(c);
  }
  return set;
}

absl::StatusOr<std::unique_ptr<ReplicaSet>> ReplicaSet::Connect(const std::vector<std::string>& names,
                                                                const std::string& address_template,
                                                                const ClientOptions& options) {
  if (address_template.find("{replica}") == std::string::npos) {
    return absl::InvalidArgumentError("ReplicaSet: the address template needs {replica}");
  }
  std::map<std::string, std::string> addresses;
  for (const std::string& n : names) addresses[n] = absl::StrReplaceAll(address_template, {{"{replica}", n}});
  return Connect(addresses, options);
}

absl::StatusOr<Client*> ReplicaSet::Replica(std::string_view name) {
  auto it = clients_.find(name);
  if (it == clients_.end()) return absl::NotFoundError(absl::StrCat("no replica named '", std::string(name), "' in this set"));
  return it->second.get();
}

absl::StatusOr<Client*> ReplicaSet::Owner(std::string_view id) {
  const std::string_view replica = ReplicaOfId(id);
  return replica.empty() ? clients_.begin()->second.get() : Replica(replica);
}

std::vector<Client*> ReplicaSet::Rotation() {
  std::vector<Client*> all;
  for (auto& [name, c] : clients_) all.push_back(c.get());
  size_t first;
  {
    std::lock_guard<std::mutex> lock(mu_);
    first = turn_++ % all.size();
  }
  std::rotate(all.begin(), all.begin() + static_cast<std::ptrdiff_t>(first), all.end());
  return all;
}

std::vector<std::string> ReplicaSet::names() const {
  std::vector<std::string> out;
  for (const auto& [name, c] : clients_) out.push_back(name);
  return out;
}

absl::StatusOr<v1::RenderResponse> ReplicaSet::Render(const v1::RenderRequest& request) {
  return Any<v1::RenderResponse>([&](Client& c) { return c.Render(request); });
}

absl::StatusOr<v1::Session> ReplicaSet::CreateSession(const v1::CreateSessionRequest& request) {
  return Any<v1::Session>([&](Client& c) { return c.CreateSession(request); });
}

absl::StatusOr<v1::StepResponse> ReplicaSet::Step(const v1::StepRequest& request, double timeout_s) {
  absl::StatusOr<Client*> c = Owner(request.session_id());
  if (!c.ok()) return c.status();
  return (*c)->Step(request, timeout_s);
}

absl::Status ReplicaSet::CloseSession(const std::string& id) {
  absl::StatusOr<Client*> c = Owner(id);
  if (!c.ok()) return c.status();
  return (*c)->CloseSession(id);
}

absl::StatusOr<v1::Job> ReplicaSet::CreateTrainingJob(const v1::CreateTrainingJobRequest& request) {
  return Any<v1::Job>([&](Client& c) { return c.CreateTrainingJob(request); });
}

absl::StatusOr<v1::Job> ReplicaSet::GetJob(const std::string& id) {
  absl::StatusOr<Client*> c = Owner(id);
  if (!c.ok()) return c.status();
  return (*c)->GetJob(id);
}

absl::StatusOr<v1::Job> ReplicaSet::CancelJob(const std::string& id) {
  absl::StatusOr<Client*> c = Owner(id);
  if (!c.ok()) return c.status();
  return (*c)->CancelJob(id);
}

}  // namespace streetsim::client
