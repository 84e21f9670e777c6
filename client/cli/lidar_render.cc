// streetsim render --lidar: one LiDAR sweep of a PLY scene from a POSE.json (docs/lidar.md).
//
//   streetsim render --lidar --ply SCENE.ply --pose POSE.json [--columns 2048]
//       [--out-range R.tiff] [--out-lidar-png P.png] [--out-points X.ply] [--points-frame sensor|ego]
//       [--alpha-threshold 0.5 | --drop-seed S] [--max-range 120] [--min-range 2.5]
//       [--backend cpu|vulkan|auto]
//
// POSE.json: {"T_world_from_lidar": [16 numbers, row-major 4x4], "time_us": T (optional, the
// sweep start; per-point times add the column offset), "T_ego_from_lidar": [16] (optional, for
// --points-frame ego; identity when absent)}. The sensor is KITTI's HDL-64E (64 beams).
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>

#include <nlohmann/json.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "client/cli/image_io.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "render/vulkan/lidar_renderer_vk.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim {
namespace {

int FailLidarRender(int code, const absl::Status& status) { return ReportFailure("render --lidar", code, status); }

struct LidarPose {
  Eigen::Isometry3d T_world_from_lidar = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d T_ego_from_lidar = Eigen::Isometry3d::Identity();
  int64_t time_us = 0;
};

absl::StatusOr<Eigen::Isometry3d> Matrix(const nlohmann::json& j, const char* key) {
  const nlohmann::json& t = j.at(key);
  if (!t.is_array() || t.size() != 16) {
    return absl::InvalidArgumentError(absl::StrCat("\"", key, "\" must be an array of 16 numbers (row-major 4x4)"));
  }
  Eigen::Matrix4d m;
  for (int i = 0; i < 16; ++i) {
    if (!t[i].is_number()) return absl::InvalidArgumentError(absl::StrCat("\"", key, "\"[", i, "] is not a number"));
    m(i / 4, i % 4) = t[i].get<double>();
  }
  const Eigen::Matrix3d R = m.topLeftCorner<3, 3>();
  if (!m.allFinite() || !(R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) ||
      R.determinant() < 0 || !m.row(3).isApprox(Eigen::RowVector4d(0, 0, 0, 1))) {
    return absl::InvalidArgumentError(absl::StrCat("\"", key, "\" is not a finite rigid transform"));
  }
  Eigen::Isometry3d T;
  T.matrix() = m;
  return T;
}

absl::StatusOr<LidarPose> ReadPoseJson(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) return absl::NotFoundError(absl::StrCat(path, ": cannot open pose file"));
  std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  if (text.size() > (1 << 20)) return absl::InvalidArgumentError(absl::StrCat(path, ": pose file larger than 1 MiB"));
  const nlohmann::json j = nlohmann::json::parse(text, nullptr, /*allow_exceptions=*/false);
  auto err = [&](const std::string& m) { return absl::InvalidArgumentError(absl::StrCat(path, ": ", m)); };
  if (j.is_discarded() || !j.is_object()) return err("pose JSON must be an object");
  for (const auto& item : j.items()) {
    if (item.key() != "T_world_from_lidar" && item.key() != "T_ego_from_lidar" && item.key() != "time_us") {
      return err(absl::StrCat("unknown pose field \"", item.key(), "\""));
    }
  }
  if (!j.contains("T_world_from_lidar")) return err("missing \"T_world_from_lidar\"");
  LidarPose pose;
  absl::StatusOr<Eigen::Isometry3d> T = Matrix(j, "T_world_from_lidar");
  if (!T.ok()) return err(std::string(T.status().message()));
  pose.T_world_from_lidar = *T;
  if (j.contains("T_ego_from_lidar")) {
    absl::StatusOr<Eigen::Isometry3d> E = Matrix(j, "T_ego_from_lidar");
    if (!E.ok()) return err(std::string(E.status().message()));
    pose.T_ego_from_lidar = *E;
  }
  if (j.contains("time_us")) {
    if (!j["time_us"].is_number_integer()) return err("\"time_us\" must be an integer");
    pose.time_us = j["time_us"].get<int64_t>();
  }
  return pose;
}

absl::Status CheckExtension(const std::string& path, std::initializer_list<const char*> allowed, const char* flag) {
  const std::string ext = absl::AsciiStrToLower(std::filesystem::path(path).extension().string());
  for (const char* a : allowed) {
    if (ext == a) return absl::OkStatus();
  }
  return absl::InvalidArgumentError(absl::StrCat(flag, " ", path, ": unsupported extension"));
}

// Google's Turbo colour map (polynomial approximation), t in [0, 1].
Eigen::Vector3f Turbo(float t) {
  t = std::clamp(t, 0.0f, 1.0f);
  const float t2 = t * t, t3 = t2 * t, t4 = t3 * t, t5 = t4 * t;
  const float r = 0.13572138f + 4.61539260f * t - 42.66032258f * t2 + 132.13108234f * t3 - 152.94239396f * t4 + 59.28637943f * t5;
  const float g = 0.09140261f + 2.19418839f * t + 4.84296658f * t2 - 14.18503333f * t3 + 4.27729857f * t4 + 2.82956604f * t5;
  const float b = 0.10667330f + 12.64194608f * t - 60.58204836f * t2 + 110.36276771f * t3 - 89.90310912f * t4 + 27.34824973f * t5;
  return {std::clamp(r, 0.0f, 1.0f), std::clamp(g, 0.0f, 1.0f), std::clamp(b, 0.0f, 1.0f)};
}

// Binary little-endian PLY: float x y z intensity, ushort beam column, double time_us.
absl::Status WritePointsPly(const std::string& path, const LidarPoints& pts, const char* frame) {
  const std::filesystem::path target(path);
  const std::filesystem::path tmp = target.string() + ".tmp";
  {
    std::ofstream f(tmp, std::ios::binary);
    if (!f) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
    f << "ply\nformat binary_little_endian 1.0\ncomment streetsim LiDAR points, " << frame
      << " frame, metres; time_us: microseconds\nelement vertex " << pts.size()
      << "\nproperty float x\nproperty float y\nproperty float z\nproperty float intensity\n"
         "property ushort beam\nproperty ushort column\nproperty double time_us\nend_header\n";
    for (size_t i = 0; i < pts.size(); ++i) {
      char rec[4 * 4 + 2 * 2 + 8];
      const float v[4] = {pts.xyz[i].x(), pts.xyz[i].y(), pts.xyz[i].z(), pts.intensity[i]};
      const uint16_t bc[2] = {pts.beam[i], pts.column[i]};
      const double t = static_cast<double>(pts.time_us[i]);
      std::memcpy(rec, v, 16);
      std::memcpy(rec + 16, bc, 4);
      std::memcpy(rec + 20, &t, 8);
      f.write(rec, sizeof rec);
    }
    if (!f) return absl::DataLossError(absl::StrCat(path, ": write failed"));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, target, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(path, ": ", ec.message()));
  return absl::OkStatus();
}

absl::StatusOr<double> PositiveNumber(const std::string& text, const char* flag) {
  double v;
  if (!absl::SimpleAtod(text, &v) || !std::isfinite(v) || v < 0) {
    return absl::InvalidArgumentError(absl::StrCat(flag, " '", text, "' is not a non-negative number"));
  }
  return v;
}

}  // namespace

int RunLidarRenderCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(
      argv, {{"lidar", false}, {"ply"}, {"pose"}, {"columns"}, {"out-range"}, {"out-lidar-png"},
             {"out-points"}, {"points-frame"}, {"alpha-threshold"}, {"drop-seed"}, {"min-range"},
             {"max-range"}, {"backend"}});
  if (!args.ok()) return FailLidarRender(2, args.status());
  if (!args->positional().empty()) {
    return FailLidarRender(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  absl::StatusOr<std::string> ply = args->Required("ply");
  if (!ply.ok()) return FailLidarRender(2, ply.status());
  absl::StatusOr<std::string> pose_path = args->Required("pose");
  if (!pose_path.ok()) return FailLidarRender(2, pose_path.status());
  const std::string out_range = args->Get("out-range").value_or("");
  const std::string out_png = args->Get("out-lidar-png").value_or("");
  const std::string out_points = args->Get("out-points").value_or("");
  if (out_range.empty() && out_png.empty() && out_points.empty()) {
    return FailLidarRender(2, absl::InvalidArgumentError("give at least one of --out-range, --out-lidar-png, --out-points"));
  }
  if (!out_range.empty()) {
    if (absl::Status s = CheckExtension(out_range, {".tif", ".tiff"}, "--out-range"); !s.ok()) return FailLidarRender(2, s);
  }
  if (!out_png.empty()) {
    if (absl::Status s = CheckExtension(out_png, {".png"}, "--out-lidar-png"); !s.ok()) return FailLidarRender(2, s);
  }
  if (!out_points.empty()) {
    if (absl::Status s = CheckExtension(out_points, {".ply"}, "--out-points"); !s.ok()) return FailLidarRender(2, s);
  }
  const std::string backend = args->Get("backend").value_or("cpu");
  if (backend != "cpu" && backend != "auto" && backend != "vulkan") {
    return FailLidarRender(2, absl::InvalidArgumentError(absl::StrCat("unknown backend '", backend, "'")));
  }
  // As the camera's --backend: auto takes vulkan only on a real GPU (lavapipe is slower than the
  // cpu renderer on the same cores); vulkan is lavapipe unless STREETSIM_VK_DEVICE names another.
  const bool use_vulkan = backend == "vulkan" || (backend == "auto" && HasVulkanGpu());
  LidarModel model = KittiHdl64e(2048);
  if (auto c = args->Get("columns")) {
    int v;
    if (!absl::SimpleAtoi(*c, &v) || v < 1 || v > 65536) {
      return FailLidarRender(2, absl::InvalidArgumentError(absl::StrCat("--columns '", *c, "' is not in 1..65536")));
    }
    model.columns = v;
  }
  for (const char* flag : {"min-range", "max-range"}) {
    if (auto t = args->Get(flag)) {
      absl::StatusOr<double> v = PositiveNumber(*t, flag);
      if (!v.ok()) return FailLidarRender(2, v.status());
      (std::strcmp(flag, "min-range") == 0 ? model.min_range_m : model.max_range_m) = *v;
    }
  }
  LidarRenderOptions options;
  if (auto t = args->Get("alpha-threshold")) {
    absl::StatusOr<double> v = PositiveNumber(*t, "--alpha-threshold");
    if (!v.ok() || *v > 1) return FailLidarRender(2, absl::InvalidArgumentError("--alpha-threshold must be in [0, 1]"));
    options.return_alpha_threshold = static_cast<float>(*v);
  }
  if (auto t = args->Get("drop-seed")) {
    if (args->Has("alpha-threshold")) {
      return FailLidarRender(2, absl::InvalidArgumentError("--drop-seed (sampled drop) and --alpha-threshold exclude each other"));
    }
    uint64_t seed;
    if (!absl::SimpleAtoi(*t, &seed)) return FailLidarRender(2, absl::InvalidArgumentError("--drop-seed must be an integer"));
    options.sample_drop = true;
    options.seed = seed;
  }
  const std::string frame = args->Get("points-frame").value_or("sensor");
  if (frame != "sensor" && frame != "ego") {
    return FailLidarRender(2, absl::InvalidArgumentError("--points-frame is sensor or ego"));
  }
  options.point_frame = frame == "ego" ? LidarRenderOptions::PointFrame::kEgo : LidarRenderOptions::PointFrame::kSensor;
  options.want_points = !out_points.empty();

  absl::StatusOr<LidarPose> pose = ReadPoseJson(*pose_path);
  if (!pose.ok()) return FailLidarRender(2, pose.status());
  model.T_ego_from_lidar = pose->T_ego_from_lidar;
  options.sweep_start_us = pose->time_us;
  if (absl::Status s = model.Validate(); !s.ok()) return FailLidarRender(2, s);
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(*ply);
  if (!store.ok()) return FailLidarRender(2, store.status());

  LidarRenderOutput out;
  std::string device = "cpu";
  if (use_vulkan) {
    absl::StatusOr<std::unique_ptr<VulkanLidarRenderer>> vk = VulkanLidarRenderer::Create(
        backend == "vulkan" ? VulkanDevicePreference::kLavapipe : VulkanDevicePreference::kGpu);
    if (!vk.ok()) return FailLidarRender(1, vk.status());
    device = (*vk)->device_name();
    if (absl::Status s = (*vk)->Render(*store, model, pose->T_world_from_lidar, options, &out); !s.ok()) {
      return FailLidarRender(1, s);
    }
  } else {
    LidarRenderer renderer;
    if (absl::Status s = renderer.Render(*store, model, pose->T_world_from_lidar, options, &out); !s.ok()) {
      return FailLidarRender(1, s);
    }
  }
  if (!out_range.empty()) {
    if (absl::Status s = WriteFloatTiff(out_range, out.columns, out.beams, out.range); !s.ok()) return FailLidarRender(1, s);
  }
  if (!out_png.empty()) {
    // Turbo over [0, min(max range, 80 m)] (blue near, red far); black where no return.
    const float scale = static_cast<float>(std::min(model.max_range_m, 80.0));
    std::vector<float> rgb(out.range.size() * 3, 0.0f);
    for (size_t p = 0; p < out.range.size(); ++p) {
      if (out.range[p] <= 0) continue;
      const Eigen::Vector3f c = Turbo(out.range[p] / scale);
      for (int k = 0; k < 3; ++k) rgb[p * 3 + k] = c[k];
    }
    if (absl::Status s = WriteRgb8(out_png, out.columns, out.beams, rgb); !s.ok()) return FailLidarRender(1, s);
  }
  if (!out_points.empty()) {
    if (absl::Status s = WritePointsPly(out_points, out.points, frame.c_str()); !s.ok()) return FailLidarRender(1, s);
  }
  size_t returns = 0;
  for (float r : out.range) returns += r > 0;
  std::fprintf(stderr,
               "streetsim render --lidar: %dx%d (%s), %zu Gaussians (%zu splats, %zu tile instances), "
               "%zu returns on %s: %.1f ms (projection %.1f, sort %.1f, blend %.1f)\n",
               out.beams, out.columns, model.name.c_str(), out.num_gaussians, out.num_visible,
               out.num_tile_instances, returns, device.c_str(), out.total_ms, out.projection_ms, out.sort_ms, out.blend_ms);
  return 0;
}

}  // namespace streetsim
