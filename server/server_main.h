// Runs a server until SIGTERM / SIGINT, then drains it (health NOT_SERVING, in-flight calls
// finish, jobs stop resumably). Used by `streetsim serve` (client/cli/serve_command.cc).
#pragma once

#include "server/server.h"

namespace streetsim::server {

// The serving process's allocator settings (RunServerUntilSignal applies them; an in-process server
// such as bench/step_bench calls this to measure what `streetsim serve` holds).
void ConfigureServingAllocator();

// Exit code: 0 after a clean shutdown, 1 if the server could not start, 2 for bad options.
int RunServerUntilSignal(const ServerOptions& options);

}  // namespace streetsim::server
