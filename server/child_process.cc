#include "server/child_process.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <thread>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

extern char** environ;

namespace streetsim::server {
namespace fs = std::filesystem;

absl::StatusOr<pid_t> SpawnLoggedChild(const std::vector<std::string>& argv, const std::string& log_path) {
  if (argv.empty()) return absl::InvalidArgumentError("no program to start");
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 1, log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&actions, 1, 2);
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t none;
  sigemptyset(&none);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETPGROUP);
  posix_spawnattr_setpgroup(&attr, 0);
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  std::vector<std::string> env_strings = {absl::StrCat("STREETSIM_PARENT_PID=", getpid())};
  for (char** e = environ; *e != nullptr; ++e) {
    if (std::strncmp(*e, "STREETSIM_PARENT_PID=", 21) != 0) env_strings.emplace_back(*e);
  }
  std::vector<char*> env;
  for (std::string& e : env_strings) env.push_back(e.data());
  env.push_back(nullptr);
  pid_t pid = 0;
  const int rc = posix_spawn(&pid, args[0], &actions, &attr, args.data(), env.data());
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attr);
  if (rc != 0) return absl::FailedPreconditionError(absl::StrCat("cannot start ", argv[0], ": ", strerror(rc)));
  return pid;
}

void EndChildGroup(pid_t pid, int grace_ms) {
  int wstatus = 0;
  kill(-pid, SIGTERM);
  for (int i = 0; i < grace_ms / 20 && waitpid(pid, &wstatus, WNOHANG) == 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  if (waitpid(pid, &wstatus, WNOHANG) == 0) {
    kill(-pid, SIGKILL);
    waitpid(pid, &wstatus, 0);
  }
}

absl::StatusOr<PipedChild> SpawnWithPipedStdout(const std::vector<std::string>& argv, const std::string& stderr_path) {
  if (argv.empty()) return absl::InvalidArgumentError("no program to start");
  int fds[2];
  if (pipe2(fds, O_CLOEXEC) != 0) return absl::InternalError(absl::StrCat("pipe: ", strerror(errno)));
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_adddup2(&actions, fds[1], 1);
  posix_spawn_file_actions_addopen(&actions, 2, stderr_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t none;
  sigemptyset(&none);
  posix_spawnattr_setsigmask(&attr, &none);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK);
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  PipedChild child;
  const int rc = posix_spawn(&child.pid, args[0], &actions, &attr, args.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attr);
  close(fds[1]);
  if (rc != 0) {
    close(fds[0]);
    return absl::FailedPreconditionError(absl::StrCat("cannot start ", argv[0], ": ", strerror(rc)));
  }
  child.stdout_fd = fds[0];
  return child;
}

bool HelpListsCommand(const std::string& program, const std::string& command) {
  std::error_code ec;
  if (!fs::exists(program, ec)) return false;
  absl::StatusOr<PipedChild> child = SpawnWithPipedStdout({program, "--help"}, "/dev/null");
  if (!child.ok()) return false;
  const int fd = child->stdout_fd;
  const pid_t pid = child->pid;
  std::string out;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (out.size() < (1 << 20)) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) break;
    pollfd pfd{fd, POLLIN, 0};
    if (poll(&pfd, 1, static_cast<int>(left.count())) <= 0) break;
    char buf[4096];
    const ssize_t n = read(fd, buf, sizeof(buf));
    if (n <= 0) break;
    out.append(buf, n);
  }
  close(fd);
  int wstatus = 0;
  if (waitpid(pid, &wstatus, WNOHANG) == 0) {
    kill(pid, SIGKILL);
    waitpid(pid, &wstatus, 0);
  }
  const std::string line = "  " + command + " ";
  return out.find("\n" + line) != std::string::npos || out.rfind(line, 0) == 0;
}

LogTail::LogTail(std::string path, std::function<bool(const std::string&)> on_line)
    : path_(std::move(path)), on_line_(std::move(on_line)) {
  std::error_code ec;
  const auto size = fs::file_size(path_, ec);
  offset_ = ec ? 0 : static_cast<long long>(size);
}

bool LogTail::Read() {
  if (!on_line_) return false;
  std::ifstream in(path_, std::ios::binary);
  if (!in) return false;
  in.seekg(offset_);
  bool changed = false;
  char buf[65536];
  while (in.read(buf, sizeof(buf)) || in.gcount() > 0) {
    const std::streamsize n = in.gcount();
    offset_ += n;
    for (std::streamsize i = 0; i < n; ++i) {
      if (buf[i] == '\n' || buf[i] == '\r') {
        if (!partial_.empty() && on_line_(partial_)) changed = true;
        partial_.clear();
      } else if (partial_.size() < 4096) {
        partial_.push_back(buf[i]);
      }
    }
  }
  return changed;
}

bool LogTail::Flush() {
  bool changed = Read();
  if (!partial_.empty() && on_line_ && on_line_(partial_)) changed = true;
  partial_.clear();
  return changed;
}

}  // namespace streetsim::server
