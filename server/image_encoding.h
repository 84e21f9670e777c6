// Encoding render outputs into v1::Image messages (RAW / PNG / JPEG via OpenCV imencode).
#pragma once

#include <vector>

#include "absl/status/status.h"
#include "streetsim/v1/common.pb.h"

namespace streetsim::server {

// Metres per unit of 16-bit PNG depth (KITTI convention: value / 256; max ~256 m; 0 = no depth).
inline constexpr double kDepthPng16Scale = 1.0 / 256.0;

// Linear RGB floats [H*W*3] -> 8 bit (clamp [0,1] x 255, rounded), then RAW / PNG / JPEG.
absl::Status EncodeRgb(int width, int height, const std::vector<float>& rgb,
                       v1::ImageEncoding encoding, int jpeg_quality, v1::Image* out);
// Depth metres: F32 raw little-endian, or PNG16 with kDepthPng16Scale.
absl::Status EncodeDepth(int width, int height, const std::vector<float>& depth,
                         v1::DepthEncoding encoding, v1::Image* out);
// Alpha: RAW float32 or PNG 8 bit (alpha x 255).
absl::Status EncodeAlpha(int width, int height, const std::vector<float>& alpha,
                         v1::ImageEncoding encoding, v1::Image* out);

}  // namespace streetsim::server
