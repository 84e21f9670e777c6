// The server's configurable limits (advertised in ServerInfo.limits).
#pragma once

#include <cstdint>

#include "render/camera.h"

namespace streetsim::server {

struct ServerLimits {
  int max_image_width = kMaxImageSide;
  int max_image_height = kMaxImageSide;
  int64_t max_message_bytes = 64 << 20;   // send and receive
  int max_sessions = 16;
  int max_queued_renders = 8;             // waiting for the renderer (beyond the running one)
  int max_trajectory_poses = 10000;
  int max_sensors_per_request = 8;
  int64_t session_lease_ms = 300'000;
  int max_concurrent_jobs = 1;
  int max_jobs = 1000;                    // records kept
};

}  // namespace streetsim::server
