// The order in which renders reach the one engine: one render at a time; those waiting are
// served round-robin across clients (a client's own requests in arrival order), so a client that
// floods the server waits behind everyone else's next request instead of in front of it. The
// queue is bounded twice: in all (Limits.max_queued_renders) and per client
// (Limits.max_queued_renders_per_client); beyond either, RESOURCE_EXHAUSTED at once.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <mutex>
#include <string>

#include "absl/status/status.h"

namespace streetsim::server {

class FairGate {
 public:
  FairGate(int max_waiting, int max_waiting_per_client);

  // Held while rendering; its destructor lets the next client in.
  class Pass {
   public:
    Pass() = default;
    Pass(Pass&& o) noexcept : gate_(o.gate_) { o.gate_ = nullptr; }
    Pass& operator=(Pass&& o) noexcept;
    Pass(const Pass&) = delete;
    Pass& operator=(const Pass&) = delete;
    ~Pass();

   private:
    friend class FairGate;
    explicit Pass(FairGate* gate) : gate_(gate) {}
    FairGate* gate_ = nullptr;
  };

  // Waits for this client's turn. `cancel` is polled while waiting (every few ms): its non-OK
  // status leaves the queue and is returned. RESOURCE_EXHAUSTED when the queue or the client's
  // share of it is full.
  absl::Status Enter(const std::string& client, const std::function<absl::Status()>& cancel, Pass* pass);

  int in_flight() const;  // rendering (0 or 1) + waiting

 private:
  void Release();

  const int max_waiting_;
  const int max_waiting_per_client_;
  mutable std::mutex mu_;
  std::condition_variable cv_;
  bool busy_ = false;
  uint64_t next_ticket_ = 0;
  uint64_t granted_ = 0;  // the ticket handed the pass by the last Release (0: none)
  int waiting_ = 0;
  std::map<std::string, std::deque<uint64_t>> queues_;  // per client, in arrival order
  std::deque<std::string> turns_;                       // clients with a waiting request, next first
};

}  // namespace streetsim::server
