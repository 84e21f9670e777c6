// ms per LiDAR sweep (cpu renderer, render/lidar/; or the vulkan one, render/vulkan/lidar_renderer_vk.h)
// on the synthetic street.
//   lidar_bench [gaussians=500000] [columns=2048] [repeats=10] [simd|scalar|vulkan]
// The scene is uploaded once (LidarRenderer::Upload: validation + SoA copy, not timed per sweep).
// The sensor sits 1.73 m up at x = 20 m, looking down the street (+x), KITTI HDL-64E beams.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "render/vulkan/lidar_renderer_vk.h"
#include "bench/lidar_bench_setup.h"
#include "scene/gaussians/synthetic_street.h"

int main(int argc, char** argv) {
  using namespace streetsim;
  bench::LidarBenchSetup setup;
  if (!bench::ParseLidarBenchSetup(argc, argv, 10, &setup)) return 2;
  const int columns = setup.columns;
  const int repeats = setup.repeats;
  const std::string& kernel = setup.kernel;
  LidarRenderOptions opt = setup.opt;
  const GaussianStore& store = setup.store;
  const LidarModel& model = setup.model;
  const Eigen::Isometry3d T_wl = setup.T_world_from_lidar;
  LidarRenderer renderer;
  LidarRenderOutput out;
  // vulkan: lavapipe unless STREETSIM_VK_DEVICE names another device.
  std::unique_ptr<VulkanLidarRenderer> vk;
  std::string device = LidarRenderer::SimdIsa();
  if (kernel == "vulkan") {
    auto created = VulkanLidarRenderer::Create();
    if (!created.ok()) {
      std::fprintf(stderr, "%s\n", std::string(created.status().message()).c_str());
      return 1;
    }
    vk = *std::move(created);
    device = vk->device_name();
  }
  if (absl::Status s = vk ? vk->Upload(store) : renderer.Upload(store); !s.ok()) {
    std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
    return 1;
  }
  std::vector<double> total, proj, sort, blend;
  for (int i = 0; i < repeats + 1; ++i) {
    if (absl::Status s = vk ? vk->Render(model, T_wl, opt, &out) : renderer.Render(model, T_wl, opt, &out);
        !s.ok()) {
      std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
      return 1;
    }
    if (i == 0) continue;  // warm-up
    total.push_back(out.total_ms);
    proj.push_back(out.projection_ms);
    sort.push_back(out.sort_ms);
    blend.push_back(out.blend_ms);
  }
  auto med = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  size_t returns = 0;
  for (float r : out.range) returns += r > 0;
  std::printf("lidar %dx%d (%s, %s), %zu Gaussians (%zu splats, %zu tile instances, %zu returns): "
              "median %.1f ms (projection %.1f, sort+bin %.1f, blend %.1f) over %d sweeps\n",
              model.beams(), columns, kernel.c_str(), device.c_str(), store.size(), out.num_visible, out.num_tile_instances, returns,
              med(total), med(proj), med(sort), med(blend), repeats);
  return 0;
}
