// Validation of the request fields shared by RenderService and SessionService.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/limits.h"
#include "server/scene_manifest.h"
#include "streetsim/v1/common.pb.h"

namespace streetsim::server {

// Enum values known, JPEG only for RGB, quality 0..100, background finite in [0,1]. When no
// output is asked for, rgb is. Returns the normalised spec.
absl::StatusOr<v1::OutputSpec> ValidateOutputs(const v1::OutputSpec& outputs);

// Resolves requested sensors against the scene rig (empty request: the whole rig). Unknown
// sensor without full intrinsics + extrinsics: NOT_FOUND; duplicates, too many, bad intrinsics,
// sizes above the limits: INVALID_ARGUMENT.
absl::StatusOr<std::vector<RigCamera>> ResolveSensors(
    const SceneManifest& manifest, const google::protobuf::RepeatedPtrField<v1::SensorRequest>& sensors,
    const ServerLimits& limits);

// OUT_OF_RANGE outside the scene's time range (static scenes accept any time).
absl::Status CheckTime(const SceneManifest& manifest, int64_t time_us);

}  // namespace streetsim::server
