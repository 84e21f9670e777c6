#include "server/request_validation.h"

#include <cmath>
#include <set>

#include "absl/strings/str_cat.h"
#include "server/echo.h"

namespace streetsim::server {

absl::StatusOr<v1::OutputSpec> ValidateOutputs(const v1::OutputSpec& in) {
  v1::OutputSpec out = in;
  if (!v1::ImageEncoding_IsValid(in.rgb_encoding())) {
    return absl::InvalidArgumentError("outputs.rgb_encoding: unknown value");
  }
  if (!v1::DepthEncoding_IsValid(in.depth_encoding())) {
    return absl::InvalidArgumentError("outputs.depth_encoding: unknown value");
  }
  if (!v1::ImageEncoding_IsValid(in.alpha_encoding()) ||
      in.alpha_encoding() == v1::IMAGE_ENCODING_JPEG) {
    return absl::InvalidArgumentError("outputs.alpha_encoding: must be RAW or PNG");
  }
  if (in.jpeg_quality() < 0 || in.jpeg_quality() > 100) {
    return absl::InvalidArgumentError("outputs.jpeg_quality: must be in 1..100 (0 = default 90)");
  }
  if (in.has_background_rgb()) {
    for (double v : {in.background_rgb().x(), in.background_rgb().y(), in.background_rgb().z()}) {
      if (!std::isfinite(v) || v < 0 || v > 1) {
        return absl::InvalidArgumentError("outputs.background_rgb: each component must be in [0,1]");
      }
    }
  }
  if (!in.rgb() && !in.depth() && !in.alpha()) out.set_rgb(true);
  return out;
}

absl::StatusOr<std::vector<RigCamera>> ResolveSensors(
    const SceneManifest& manifest, const google::protobuf::RepeatedPtrField<v1::SensorRequest>& sensors,
    const ServerLimits& limits) {
  std::vector<RigCamera> out;
  if (sensors.empty()) {
    out = manifest.cameras;
  } else {
    std::set<std::string> seen;
    for (int i = 0; i < sensors.size(); ++i) {
      const v1::SensorRequest& req = sensors[i];
      const std::string field = absl::StrCat("sensors[", i, "]");
      if (req.sensor_id().empty()) return absl::InvalidArgumentError(field + ".sensor_id is empty");
      if (!seen.insert(req.sensor_id()).second) {
        return absl::InvalidArgumentError(absl::StrCat(field, ": duplicate sensor ", Echo(req.sensor_id())));
      }
      RigCamera cam;
      const RigCamera* rig = manifest.FindCamera(req.sensor_id());
      if (rig) {
        cam = *rig;
      } else if (!req.has_intrinsics() || !req.has_t_ego_from_sensor()) {
        return absl::NotFoundError(absl::StrCat(
            field, ": unknown sensor ", Echo(req.sensor_id()),
            " (a new sensor needs both intrinsics and T_ego_from_sensor)"));
      }
      cam.sensor_id = req.sensor_id();
      if (req.has_intrinsics()) {
        absl::StatusOr<Intrinsics> k = IntrinsicsFromProto(req.intrinsics(), field + ".intrinsics");
        if (!k.ok()) return k.status();
        cam.intrinsics = *k;
      } else if (req.width() != 0 || req.height() != 0) {
        if (req.width() <= 0 || req.height() <= 0) {
          return absl::InvalidArgumentError(field + ": width and height must both be positive");
        }
        const double sx = double(req.width()) / cam.intrinsics.width;
        const double sy = double(req.height()) / cam.intrinsics.height;
        Intrinsics& k = cam.intrinsics;
        // Pixel centres at integers: scale about the image corner (-0.5, -0.5).
        k.cx = (k.cx + 0.5) * sx - 0.5;
        k.cy = (k.cy + 0.5) * sy - 0.5;
        k.fx *= sx;
        k.fy *= sy;
        k.width = req.width();
        k.height = req.height();
      }
      if (req.has_t_ego_from_sensor()) {
        absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(req.t_ego_from_sensor(), field + ".T_ego_from_sensor");
        if (!T.ok()) return T.status();
        cam.T_ego_from_cam = *T;
      }
      out.push_back(cam);
    }
  }
  if (static_cast<int>(out.size()) > limits.max_sensors_per_request) {
    return absl::InvalidArgumentError(absl::StrCat("too many sensors (", out.size(), " > ",
                                                   limits.max_sensors_per_request, ")"));
  }
  for (const RigCamera& c : out) {
    if (c.intrinsics.width > limits.max_image_width || c.intrinsics.height > limits.max_image_height) {
      return absl::InvalidArgumentError(absl::StrCat(
          "sensor ", c.sensor_id, ": ", c.intrinsics.width, "x", c.intrinsics.height,
          " is above the server's limit of ", limits.max_image_width, "x", limits.max_image_height));
    }
  }
  return out;
}

absl::Status CheckTime(const SceneManifest& manifest, int64_t time_us) {
  if (!manifest.has_time_range) return absl::OkStatus();
  if (time_us < manifest.start_us || time_us > manifest.end_us) {
    return absl::OutOfRangeError(absl::StrCat("time_us ", time_us, " is outside the scene's range [",
                                              manifest.start_us, ", ", manifest.end_us, "]"));
  }
  return absl::OkStatus();
}

}  // namespace streetsim::server
