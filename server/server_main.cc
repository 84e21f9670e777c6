#include "server/server_main.h"

#include <malloc.h>
#include <pthread.h>
#include <signal.h>

#include <cstdio>

namespace streetsim::server {

void ConfigureServingAllocator() {
  // A served frame's buffers are megabytes (a 4096x4096 render holds ~600 MB). glibc raises its
  // mmap threshold after such blocks are freed and then keeps later ones in the heap, where one
  // large request leaves the process that much bigger for good. A fixed threshold (which turns the
  // adaptation off) keeps every block above 1 MiB in its own mapping, returned when freed.
  mallopt(M_MMAP_THRESHOLD, 1 << 20);
  mallopt(M_TRIM_THRESHOLD, 8 << 20);
}

int RunServerUntilSignal(const ServerOptions& options) {
  ConfigureServingAllocator();
  // Block the stop signals in every thread (gRPC's included, created after this) and wait for
  // them here.
  sigset_t stop;
  sigemptyset(&stop);
  sigaddset(&stop, SIGTERM);
  sigaddset(&stop, SIGINT);
  pthread_sigmask(SIG_BLOCK, &stop, nullptr);

  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  if (!server.ok()) {
    std::fprintf(stderr, "streetsim serve: %s\n", std::string(server.status().message()).c_str());
    return absl::IsInvalidArgument(server.status()) ? 2 : 1;
  }
  std::printf("streetsim serve: listening on %s\n", (*server)->address().c_str());
  std::fflush(stdout);
  int sig = 0;
  sigwait(&stop, &sig);
  std::fprintf(stderr, "streetsim serve: %s, draining\n", sig == SIGTERM ? "SIGTERM" : "SIGINT");
  (*server)->Shutdown();
  return 0;
}

}  // namespace streetsim::server
