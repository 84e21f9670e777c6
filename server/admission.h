// Admission before work: what a render request will cost (pixels, LiDAR rays, the least bytes its
// response can take) from its validated views, outputs and LiDAR job, checked against the
// server's limits before it queues, loads a scene or renders. A request refused here has
// allocated nothing; one admitted here can still be refused after encoding only when compressed
// images (PNG/JPEG) turn out larger than the message limit, which the pixel budget keeps cheap.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "server/lidar_request.h"
#include "server/limits.h"
#include "server/render_core.h"
#include "streetsim/v1/common.pb.h"

namespace streetsim::server {

struct RenderCost {
  int64_t pixels = 0;               // summed over the request's cameras
  int64_t lidar_rays = 0;           // beams x columns
  int64_t min_response_bytes = 0;   // raw outputs exactly, compressed ones as 0, LiDAR arrays
};

// The cost of one render (one Render call, one step, one trajectory point). `outputs` validated.
RenderCost EstimateRenderCost(const std::vector<CameraView>& views, const v1::OutputSpec& outputs,
                              const LidarJob* lidar);

// RESOURCE_EXHAUSTED naming the limit and what to change: more pixels than
// limits.max_request_pixels, more rays than limits.max_lidar_rays, or a response that cannot fit
// limits.max_message_bytes even at its smallest.
absl::Status AdmitRender(const RenderCost& cost, const ServerLimits& limits);

}  // namespace streetsim::server
