#include "server/fair_gate.h"

#include <algorithm>
#include <chrono>

#include "absl/strings/str_cat.h"

namespace streetsim::server {

FairGate::FairGate(int max_waiting, int max_waiting_per_client)
    : max_waiting_(std::max(0, max_waiting)), max_waiting_per_client_(std::max(1, max_waiting_per_client)) {}

FairGate::Pass& FairGate::Pass::operator=(Pass&& o) noexcept {
  if (this != &o) {
    if (gate_) gate_->Release();
    gate_ = o.gate_;
    o.gate_ = nullptr;
  }
  return *this;
}

FairGate::Pass::~Pass() {
  if (gate_) gate_->Release();
}

absl::Status FairGate::Enter(const std::string& client, const std::function<absl::Status()>& cancel, Pass* pass) {
  std::unique_lock<std::mutex> lock(mu_);
  if (!busy_ && waiting_ == 0) {
    busy_ = true;
    *pass = Pass(this);
    return absl::OkStatus();
  }
  if (waiting_ >= max_waiting_) {
    return absl::ResourceExhaustedError(
        absl::StrCat("render queue full (", max_waiting_, " waiting); retry later"));
  }
  std::deque<uint64_t>& mine = queues_[client];
  if (static_cast<int>(mine.size()) >= max_waiting_per_client_) {
    return absl::ResourceExhaustedError(absl::StrCat("this client already has ", mine.size(),
                                                     " renders waiting (the server's limit per client); retry later"));
  }
  const uint64_t ticket = ++next_ticket_;
  if (mine.empty()) turns_.push_back(client);
  mine.push_back(ticket);
  ++waiting_;
  while (granted_ != ticket) {
    cv_.wait_for(lock, std::chrono::milliseconds(5));
    if (granted_ == ticket) break;
    lock.unlock();
    absl::Status stop = cancel ? cancel() : absl::OkStatus();
    lock.lock();
    if (stop.ok() || granted_ == ticket) continue;
    // Leave the queue (the ticket is still in it: only Release takes tickets out).
    auto q = queues_.find(client);
    q->second.erase(std::find(q->second.begin(), q->second.end(), ticket));
    if (q->second.empty()) {
      queues_.erase(q);
      turns_.erase(std::find(turns_.begin(), turns_.end(), client));
    }
    --waiting_;
    return stop;
  }
  granted_ = 0;
  *pass = Pass(this);
  return absl::OkStatus();
}

void FairGate::Release() {
  std::lock_guard<std::mutex> lock(mu_);
  if (turns_.empty()) {
    busy_ = false;
    return;
  }
  const std::string client = turns_.front();
  turns_.pop_front();
  auto q = queues_.find(client);
  granted_ = q->second.front();
  q->second.pop_front();
  if (q->second.empty()) {
    queues_.erase(q);
  } else {
    turns_.push_back(client);
  }
  --waiting_;
  cv_.notify_all();  // busy_ stays true: the pass goes straight to the granted ticket
}

int FairGate::in_flight() const {
  std::lock_guard<std::mutex> lock(mu_);
  return (busy_ ? 1 : 0) + waiting_;
}

}  // namespace streetsim::server
