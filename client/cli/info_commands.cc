// streetsim ply-info and streetsim devices.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/camera_json.h"
#include "client/cli/commands.h"
#include "render/cpu/cpu_engine.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim {
namespace {

int FailInfo(const char* command, int code, const absl::Status& status) {
  return ReportFailure(command, code, status);
}

double Percentile(std::vector<float> v, double q) {
  if (v.empty()) return 0;
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * (v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

// A camera outside the scene's robust bounds (5th..95th percentile of the means) looking at
// their centre from one side, with the scene filling most of a 60-degree field of view.
PinholeCamera FramingCamera(const GaussianStore& store, int width, int height, const std::string& view) {
  Eigen::Vector3d lo, hi;
  for (int k = 0; k < 3; ++k) {
    std::vector<float> axis(store.size());
    for (size_t i = 0; i < store.size(); ++i) axis[i] = store.means[i * 3 + k];
    lo[k] = Percentile(axis, 0.05);
    hi[k] = Percentile(axis, 0.95);
  }
  const Eigen::Vector3d centre = 0.5 * (lo + hi);
  const double radius = std::max(0.5 * (hi - lo).norm(), 1e-3);
  Eigen::Vector3d forward(0, 0, 1), down(0, 1, 0);  // OpenCV-like default: look along +z
  if (view == "back") forward = {0, 0, -1};
  if (view == "left") forward = {1, 0, 0};
  if (view == "right") forward = {-1, 0, 0};
  if (view == "top") { forward = {0, 1, 0}; down = {0, 0, 1}; }
  const double fov = 60.0 * M_PI / 180.0;
  const double distance = radius / std::tan(fov / 2) * 1.1;
  Eigen::Matrix3d R;
  R.col(2) = forward;
  R.col(1) = down;
  R.col(0) = down.cross(forward);
  PinholeCamera cam;
  cam.width = width;
  cam.height = height;
  cam.fx = cam.fy = 0.5 * width / std::tan(fov / 2);
  cam.cx = (width - 1) / 2.0;
  cam.cy = (height - 1) / 2.0;
  cam.T_world_from_cam.linear() = R;
  cam.T_world_from_cam.translation() = centre - distance * forward;
  return cam;
}

}  // namespace

int RunPlyInfoCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args =
      ParsedArgs::Parse(argv, {{"camera-out"}, {"width"}, {"height"}, {"view"}});
  if (!args.ok()) return FailInfo("ply-info", 2, args.status());
  if (args->positional().size() != 1) {
    return FailInfo("ply-info", 2, absl::InvalidArgumentError("expects exactly one SCENE.ply"));
  }
  int width = 800, height = 600;
  if (auto w = args->Get("width"); w && (!absl::SimpleAtoi(*w, &width) || width < 1 || width > kMaxImageSide)) {
    return FailInfo("ply-info", 2, absl::InvalidArgumentError("--width must be in 1..4096"));
  }
  if (auto h = args->Get("height"); h && (!absl::SimpleAtoi(*h, &height) || height < 1 || height > kMaxImageSide)) {
    return FailInfo("ply-info", 2, absl::InvalidArgumentError("--height must be in 1..4096"));
  }
  const std::string view = args->Get("view").value_or("front");
  if (view != "front" && view != "back" && view != "left" && view != "right" && view != "top") {
    return FailInfo("ply-info", 2, absl::InvalidArgumentError("--view must be front, back, left, right or top"));
  }
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(args->positional()[0]);
  if (!store.ok()) return FailInfo("ply-info", 2, store.status());
  std::printf("%s: %zu Gaussians, SH degree %d, normals %s\n", args->positional()[0].c_str(),
              store->size(), store->sh_degree, store->normals.empty() ? "no" : "yes");
  if (store->size() == 0) return 0;
  for (int k = 0; k < 3; ++k) {
    std::vector<float> axis(store->size());
    for (size_t i = 0; i < store->size(); ++i) axis[i] = store->means[i * 3 + k];
    std::printf("  %c: min %.3f  p5 %.3f  median %.3f  p95 %.3f  max %.3f\n", "xyz"[k],
                Percentile(axis, 0), Percentile(axis, 0.05), Percentile(axis, 0.5),
                Percentile(axis, 0.95), Percentile(axis, 1));
  }
  if (auto out = args->Get("camera-out")) {
    std::ofstream f(*out);
    f << CameraToJson(FramingCamera(*store, width, height, view));
    if (!f.good()) return FailInfo("ply-info", 1, absl::PermissionDeniedError(absl::StrCat(*out, ": cannot write")));
    std::printf("  framing camera (%s view) written to %s\n", view.c_str(), out->c_str());
  }
  return 0;
}

int RunDevicesCommand(const std::vector<std::string>& argv) {
  if (!argv.empty()) return FailInfo("devices", 2, absl::InvalidArgumentError("takes no arguments"));
  std::printf("cpu: %s\n", CreateCpuEngine()->device_name().c_str());
  const std::vector<VulkanDeviceInfo> devices = ListVulkanDevices();
  if (devices.empty()) std::printf("vulkan: no device (no Vulkan driver installed?)\n");
  for (size_t i = 0; i < devices.size(); ++i) {
    std::printf("vulkan[%zu]: %s (%s, subgroup size %u)\n", i, devices[i].name.c_str(),
                devices[i].is_cpu ? "CPU" : "GPU", devices[i].subgroup_size);
  }
  std::printf("--backend auto picks: %s\n", HasVulkanGpu() ? "vulkan (GPU present)" : "cpu");
  return 0;
}

}  // namespace streetsim
