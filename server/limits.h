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
  // One client's share of that queue (a client: a session for steps, the caller's identity for
  // Render), so that one busy client meets backpressure while the others still get in.
  int max_queued_renders_per_client = 2;
  // Pixels per render summed over its cameras: one 4096x4096 camera, or eight 1920x1080. Bounds
  // the host memory of a render (~36 B per pixel: float buffers plus encoding) at ~600 MB.
  int64_t max_request_pixels = int64_t{4096} * 4096;
  int64_t max_lidar_rays = int64_t{128} * 65536;  // beams x columns per sweep
  int max_trajectory_poses = 10000;
  int max_sensors_per_request = 8;
  int64_t session_lease_ms = 300'000;
  int max_concurrent_jobs = 1;
  int max_jobs = 1000;                    // records kept
};

}  // namespace streetsim::server
