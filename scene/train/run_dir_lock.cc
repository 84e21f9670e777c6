#include "scene/train/run_dir_lock.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace streetsim::train {

namespace {

// The holder writes its pid into the file, for the message a refused trainer prints.
std::string HolderPid(int fd) {
  char buf[32] = {};
  const ssize_t n = pread(fd, buf, sizeof(buf) - 1, 0);
  int pid = 0;
  if (n > 0 && absl::SimpleAtoi(std::string(buf, static_cast<size_t>(n)), &pid) && pid > 0) {
    return absl::StrCat("pid ", pid);
  }
  return "another process";
}

}  // namespace

absl::StatusOr<RunDirLock> RunDirLock::Acquire(const std::string& dir, double wait_s) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return absl::FailedPreconditionError(absl::StrCat("cannot create ", dir, ": ", ec.message()));
  const std::string path = (std::filesystem::path(dir) / ".train.lock").string();
  const int fd = open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd < 0) return absl::FailedPreconditionError(absl::StrCat("cannot open ", path, ": ", std::strerror(errno)));
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(std::max(0.0, wait_s));
  while (flock(fd, LOCK_EX | LOCK_NB) != 0) {
    if (errno != EWOULDBLOCK && errno != EINTR) {
      const int e = errno;
      close(fd);
      return absl::FailedPreconditionError(absl::StrCat("cannot lock ", path, ": ", std::strerror(e)));
    }
    if (std::chrono::steady_clock::now() >= deadline) {
      const std::string holder = HolderPid(fd);
      close(fd);
      return absl::FailedPreconditionError(absl::StrCat(
          dir, " is being written by another `streetsim train` (", holder, " holds ", path,
          "); wait for it to end or stop it, then --resume"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  // The pid is only for the message a refused trainer prints; the lock is held either way.
  const std::string pid = absl::StrCat(getpid(), "\n");
  if (ftruncate(fd, 0) == 0) {
    [[maybe_unused]] const ssize_t n = pwrite(fd, pid.data(), pid.size(), 0);
  }
  return RunDirLock(fd, path);
}

RunDirLock::RunDirLock(RunDirLock&& other) noexcept : fd_(other.fd_), path_(std::move(other.path_)) { other.fd_ = -1; }

RunDirLock& RunDirLock::operator=(RunDirLock&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) close(fd_);
    fd_ = other.fd_;
    path_ = std::move(other.path_);
    other.fd_ = -1;
  }
  return *this;
}

RunDirLock::~RunDirLock() {
  if (fd_ >= 0) close(fd_);  // closing the last descriptor releases the lock
}

}  // namespace streetsim::train
