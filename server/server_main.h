// Runs a server until SIGTERM / SIGINT, then drains it (health NOT_SERVING, in-flight calls
// finish, jobs stop resumably). Used by `streetsim serve` (client/cli/serve_command.cc).
#pragma once

#include "server/server.h"

namespace streetsim::server {

// Exit code: 0 after a clean shutdown, 1 if the server could not start, 2 for bad options.
int RunServerUntilSignal(const ServerOptions& options);

}  // namespace streetsim::server
