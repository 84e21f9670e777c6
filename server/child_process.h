// The child processes of training jobs (server/job_runner.h): started in their own process group
// with their output appended to a log, their log read line by line as it grows, and ended with
// the group.
#pragma once

#include <sys/types.h>

#include <functional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace streetsim::server {

// Starts argv (argv[0]: a path) with stdin from /dev/null, stdout and stderr appended to
// log_path, no blocked signals (the server blocks SIGTERM in its threads), in a process group of
// its own, and STREETSIM_PARENT_PID set to this process so that it ends with the server, even
// with a `kill -9` of it (client/cli/parent_server.h). FAILED_PRECONDITION "cannot start ..."
// when it cannot be started.
absl::StatusOr<pid_t> SpawnLoggedChild(const std::vector<std::string>& argv, const std::string& log_path);

// A child whose stdout the caller reads.
struct PipedChild {
  pid_t pid = -1;
  int stdout_fd = -1;  // the pipe's read end (close-on-exec); the caller closes it
};

// Starts argv (argv[0]: a path) with stdin from /dev/null, stdout into a pipe, stderr truncated
// into stderr_path ("/dev/null": dropped) and no blocked signals, in this process's group.
// FAILED_PRECONDITION "cannot start ..." when it cannot be started.
absl::StatusOr<PipedChild> SpawnWithPipedStdout(const std::vector<std::string>& argv, const std::string& stderr_path);

// SIGTERM to the child's group; SIGKILL when it has not exited after grace_ms. Reaps it.
void EndChildGroup(pid_t pid, int grace_ms);

// Whether `program --help` (10 s at most) lists `command` as a command line ("  command ...").
bool HelpListsCommand(const std::string& program, const std::string& command);

// The lines a growing log gains, from the size it had when the tail was made: each complete line
// (ended by \n or \r, at most 4096 bytes kept) goes to on_line, whose result says whether it
// changed something (Read returns whether any line did).
class LogTail {
 public:
  LogTail(std::string path, std::function<bool(const std::string&)> on_line);
  bool Read();
  // Passes on a last line without its end (the child has exited).
  bool Flush();

 private:
  std::string path_;
  std::function<bool(const std::string&)> on_line_;
  long long offset_ = 0;
  std::string partial_;
};

}  // namespace streetsim::server
