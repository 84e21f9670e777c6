// Durable training-job records: <state_dir>/jobs/<job_id>/job.json (the v1::Job message as
// JSON), written atomically (temp file, fsync, rename). Loaded at start so that jobs survive
// restarts. Replicas sharing a state dir (server/replica.h) each keep their own jobs in memory and
// write only those; another replica's records are read from disk when asked for.
#pragma once

#include <chrono>
#include <condition_variable>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "streetsim/v1/training.pb.h"

namespace streetsim::server {

class JobStore {
 public:
  explicit JobStore(std::string state_dir, std::string replica = "");
  // Creates the directories and loads this replica's job.json files (unreadable records are
  // logged, skipped).
  absl::Status Init();

  // This replica's jobs, then the other replicas' as their records on disk say now.
  std::vector<v1::Job> List();
  std::optional<v1::Job> Get(const std::string& id);
  std::optional<v1::Job> FindByRequestId(const std::string& request_id);
  // Whether this replica runs (and writes) the job: its id names this replica.
  bool Owns(const std::string& id) const;
  // Stamps updated_unix_ms, writes the record, then publishes it in memory.
  absl::Status Put(v1::Job job);
  std::string NewId();
  int size();

  std::string JobDir(const std::string& id) const { return jobs_dir_ + "/" + id; }
  const std::string& scenes_dir() const { return scenes_dir_; }

  // Version counter of the records (bumps on every Put); waits up to `timeout` for a change.
  uint64_t version();
  uint64_t WaitForChange(uint64_t seen, std::chrono::milliseconds timeout);

 private:
  std::optional<v1::Job> ReadRecord(const std::string& id) const;
  std::vector<v1::Job> ReadForeignRecords() const;

  const std::string state_dir_;
  const std::string replica_;
  const std::string jobs_dir_;
  const std::string scenes_dir_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, v1::Job> jobs_;
  uint64_t version_ = 0;
  uint64_t counter_ = 0;
};

int64_t NowUnixMs();

}  // namespace streetsim::server
