// What the gRPC services share (owned by Server).
#pragma once

#include <atomic>

#include "server/auth.h"
#include "server/limits.h"
#include "server/render_core.h"
#include "server/scene_registry.h"

namespace streetsim::server {

class SessionManager;
class JobRunner;

struct ServiceDeps {
  ServerLimits limits;
  Authenticator auth;
  bool tls = false;
  std::string replica;  // server/replica.h
  RenderCore* core = nullptr;
  SceneRegistry* scenes = nullptr;
  SessionManager* sessions = nullptr;
  JobRunner* jobs = nullptr;
  std::atomic<bool> draining{false};  // SIGTERM: new sessions / jobs refused with UNAVAILABLE
};

}  // namespace streetsim::server
