#include "client/cli/camera_json.h"

#include <cmath>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim {
namespace {

constexpr size_t kMaxCameraFileBytes = 1 << 20;

absl::StatusOr<double> Number(const nlohmann::json& j, const char* key) {
  if (!j.contains(key)) return absl::InvalidArgumentError(absl::StrCat("missing \"", key, "\""));
  const nlohmann::json& v = j.at(key);
  if (!v.is_number()) return absl::InvalidArgumentError(absl::StrCat("\"", key, "\" must be a number"));
  return v.get<double>();
}

absl::StatusOr<int> Integer(const nlohmann::json& j, const char* key) {
  absl::StatusOr<double> v = Number(j, key);
  if (!v.ok()) return v.status();
  if (*v != std::floor(*v) || *v < 1 || *v > 1e9) {
    return absl::InvalidArgumentError(absl::StrCat("\"", key, "\" must be a positive integer"));
  }
  return static_cast<int>(*v);
}

}  // namespace

absl::StatusOr<PinholeCamera> ParseCameraJson(const std::string& text) {
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) return absl::InvalidArgumentError("camera JSON does not parse");
  if (!j.is_object()) return absl::InvalidArgumentError("camera JSON must be an object");
  static const char* kKnown[] = {"width", "height", "fx", "fy", "cx", "cy", "T_world_from_cam"};
  for (const auto& item : j.items()) {
    if (std::find(std::begin(kKnown), std::end(kKnown), item.key()) == std::end(kKnown)) {
      return absl::InvalidArgumentError(absl::StrCat("unknown camera field \"", item.key(), "\""));
    }
  }
  PinholeCamera cam;
  absl::StatusOr<int> w = Integer(j, "width"), h = Integer(j, "height");
  if (!w.ok()) return w.status();
  if (!h.ok()) return h.status();
  cam.width = *w;
  cam.height = *h;
  double* fields[] = {&cam.fx, &cam.fy, &cam.cx, &cam.cy};
  const char* names[] = {"fx", "fy", "cx", "cy"};
  for (int i = 0; i < 4; ++i) {
    absl::StatusOr<double> v = Number(j, names[i]);
    if (!v.ok()) return v.status();
    *fields[i] = *v;
  }
  if (!j.contains("T_world_from_cam")) return absl::InvalidArgumentError("missing \"T_world_from_cam\"");
  const nlohmann::json& t = j.at("T_world_from_cam");
  if (!t.is_array() || t.size() != 16) {
    return absl::InvalidArgumentError("\"T_world_from_cam\" must be an array of 16 numbers (row-major 4x4)");
  }
  Eigen::Matrix4d m;
  for (int i = 0; i < 16; ++i) {
    if (!t[i].is_number()) {
      return absl::InvalidArgumentError(absl::StrCat("\"T_world_from_cam\"[", i, "] is not a number"));
    }
    m(i / 4, i % 4) = t[i].get<double>();
  }
  cam.T_world_from_cam.matrix() = m;
  if (absl::Status s = cam.Validate(); !s.ok()) return s;
  return cam;
}

absl::StatusOr<PinholeCamera> ReadCameraJson(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return absl::NotFoundError(absl::StrCat(path, ": cannot open camera file"));
  std::string text;
  text.resize(kMaxCameraFileBytes + 1);
  f.read(text.data(), static_cast<std::streamsize>(text.size()));
  text.resize(static_cast<size_t>(f.gcount()));
  if (text.size() > kMaxCameraFileBytes) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": camera file larger than 1 MiB"));
  }
  absl::StatusOr<PinholeCamera> cam = ParseCameraJson(text);
  if (!cam.ok()) {
    return absl::Status(cam.status().code(), absl::StrCat(path, ": ", cam.status().message()));
  }
  return cam;
}

std::string CameraToJson(const PinholeCamera& camera) {
  nlohmann::json j;
  j["width"] = camera.width;
  j["height"] = camera.height;
  j["fx"] = camera.fx;
  j["fy"] = camera.fy;
  j["cx"] = camera.cx;
  j["cy"] = camera.cy;
  std::vector<double> t(16);
  for (int i = 0; i < 16; ++i) t[i] = camera.T_world_from_cam.matrix()(i / 4, i % 4);
  j["T_world_from_cam"] = t;
  return j.dump(2) + "\n";
}

}  // namespace streetsim
