// CAMERA.json: {"width": W, "height": H, "fx": .., "fy": .., "cx": .., "cy": ..,
//               "T_world_from_cam": [16 numbers, row-major 4x4]}
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "render/camera.h"

namespace streetsim {

absl::StatusOr<PinholeCamera> ParseCameraJson(const std::string& text);
absl::StatusOr<PinholeCamera> ReadCameraJson(const std::string& path);
std::string CameraToJson(const PinholeCamera& camera);

}  // namespace streetsim
