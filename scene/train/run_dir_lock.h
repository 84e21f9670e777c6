// One writer per training directory: `streetsim train` holds an exclusive lock on DIR/.train.lock
// for as long as it runs, so a second trainer (a restarted server's, or a user's in the same DIR)
// cannot write beside it. The kernel drops the lock when the process dies, however it dies, so a
// stale lock file never blocks anyone.
#pragma once

#include <string>

#include "absl/status/statusor.h"

namespace streetsim::train {

class RunDirLock {
 public:
  // Takes DIR/.train.lock (creating DIR), waiting up to wait_s seconds while another process holds
  // it. FailedPrecondition naming the holder's pid and the lock file when it is still held then.
  static absl::StatusOr<RunDirLock> Acquire(const std::string& dir, double wait_s);

  RunDirLock(RunDirLock&& other) noexcept;
  RunDirLock& operator=(RunDirLock&& other) noexcept;
  RunDirLock(const RunDirLock&) = delete;
  RunDirLock& operator=(const RunDirLock&) = delete;
  ~RunDirLock();

  const std::string& path() const { return path_; }

 private:
  RunDirLock(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  int fd_ = -1;
  std::string path_;
};

}  // namespace streetsim::train
