#include "client/cli/parent_server.h"

#include <sys/prctl.h>
#include <unistd.h>

#include <csignal>
#include <cstdlib>

#include "absl/strings/numbers.h"

namespace streetsim {

namespace {
constexpr char kParentPidEnv[] = "STREETSIM_PARENT_PID";
}

bool StartedByServer() { return std::getenv(kParentPidEnv) != nullptr; }

void DieWithParentServer() {
  const char* v = std::getenv(kParentPidEnv);
  int parent = 0;
  if (v == nullptr || !absl::SimpleAtoi(v, &parent) || parent <= 1) return;
  prctl(PR_SET_PDEATHSIG, SIGHUP);
  // The parent may have died between our start and prctl: then we were re-parented already.
  if (getppid() != parent) std::raise(SIGHUP);
}

}  // namespace streetsim
