#include "server/admission.h"

#include "absl/strings/str_cat.h"

namespace streetsim::server {
namespace {

// Wire bytes per pixel (image_encoding.cc): RGB8 raw, depth and alpha raw float32. A compressed
// image has no useful lower bound (it counts 0).
constexpr int64_t kRgbRawBytes = 3;
constexpr int64_t kDepthRawBytes = 4;
constexpr int64_t kAlphaRawBytes = 4;
// Per ray (lidar_request.cc): range, intensity and alpha float32 arrays always (points only where
// a ray returns: no lower bound).
constexpr int64_t kLidarRayBytes = 12;

bool IsRaw(v1::ImageEncoding e) { return e == v1::IMAGE_ENCODING_UNSPECIFIED || e == v1::IMAGE_ENCODING_RAW; }
bool IsRaw(v1::DepthEncoding e) { return e == v1::DEPTH_ENCODING_UNSPECIFIED || e == v1::DEPTH_ENCODING_F32; }

}  // namespace

RenderCost EstimateRenderCost(const std::vector<CameraView>& views, const v1::OutputSpec& outputs,
                              const LidarJob* lidar) {
  RenderCost cost;
  for (const CameraView& v : views) {
    const int64_t px = int64_t{v.intrinsics.width} * v.intrinsics.height;
    cost.pixels += px;
    if (outputs.rgb() && IsRaw(outputs.rgb_encoding())) cost.min_response_bytes += px * kRgbRawBytes;
    if (outputs.depth() && IsRaw(outputs.depth_encoding())) cost.min_response_bytes += px * kDepthRawBytes;
    if (outputs.alpha() && IsRaw(outputs.alpha_encoding())) cost.min_response_bytes += px * kAlphaRawBytes;
  }
  if (lidar) {
    cost.lidar_rays = int64_t{lidar->model.beams()} * lidar->model.columns;
    cost.min_response_bytes += cost.lidar_rays * kLidarRayBytes;
  }
  return cost;
}

absl::Status AdmitRender(const RenderCost& cost, const ServerLimits& limits) {
  if (cost.pixels > limits.max_request_pixels) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "the request's cameras have ", cost.pixels, " pixels, above the server's limit of ",
        limits.max_request_pixels, " per render (ServerInfo.limits.max_request_pixels); ask for fewer sensors or a "
        "smaller resolution"));
  }
  if (cost.lidar_rays > limits.max_lidar_rays) {
    return absl::ResourceExhaustedError(absl::StrCat("the LiDAR request has ", cost.lidar_rays,
                                                     " rays, above the server's limit of ", limits.max_lidar_rays,
                                                     "; ask for fewer columns"));
  }
  if (cost.min_response_bytes > limits.max_message_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "the response would take at least ", cost.min_response_bytes, " bytes, above the server's max message size (",
        limits.max_message_bytes, "); ask for PNG/JPEG, fewer sensors or a smaller resolution"));
  }
  return absl::OkStatus();
}

}  // namespace streetsim::server
