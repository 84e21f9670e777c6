// ms per LiDAR sweep with a rolling sweep, and of the cpu LiDAR backward pass, on the synthetic
// street (the scene and sensor of lidar_bench).
//   lidar_backward_bench [gaussians=500000] [columns=2048] [repeats=5] [simd|scalar|vulkan]
// vulkan: VulkanLidarRenderer (lavapipe unless STREETSIM_VK_DEVICE names another device).
// Per repeat, back to back on the same uploaded scene: a static sweep, a rolling sweep (the sensor
// moves 1.5 m forward and yaws 2 degrees during it: 15 m/s at 10 Hz), then a static sweep with
// keep_for_backward and LidarRenderer::Backward with fixed pseudo-random upstream gradients on
// range_sum, alpha and intensity_sum, once in the fast and once in the deterministic mode. Medians.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <limits>
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
  if (!bench::ParseLidarBenchSetup(argc, argv, 5, &setup)) return 2;
  const int columns = setup.columns;
  const int repeats = setup.repeats;
  const std::string& kernel = setup.kernel;
  LidarRenderOptions opt = setup.opt;
  const GaussianStore& store = setup.store;
  const LidarModel& model = setup.model;
  const Eigen::Isometry3d T_wl = setup.T_world_from_lidar;
  const LidarSweepPose fixed = LidarSweepPose::Static(T_wl);
  LidarSweepPose rolling = fixed;
  rolling.T_world_from_lidar_end.translate(Eigen::Vector3d(1.5, 0, 0));
  rolling.T_world_from_lidar_end.rotate(Eigen::AngleAxisd(2 * M_PI / 180, Eigen::Vector3d::UnitZ()));
  std::vector<float> d_range, d_alpha, d_intensity;
  for (size_t p = 0; p < static_cast<size_t>(model.beams()) * columns; ++p) {
    const uint32_t h = static_cast<uint32_t>(p * 2654435761u);
    d_range.push_back(((h >> 8) & 1023) / 1023.0f - 0.5f);
    d_alpha.push_back(((h >> 18) & 1023) / 1023.0f - 0.5f);
    d_intensity.push_back(((h >> 4) & 255) / 255.0f - 0.5f);
  }
  LidarRenderer cpu_renderer;
  std::unique_ptr<VulkanLidarRenderer> vk_renderer;
  if (kernel == "vulkan") {
    auto created = VulkanLidarRenderer::Create();
    if (!created.ok()) {
      std::fprintf(stderr, "%s\n", std::string(created.status().message()).c_str());
      return 1;
    }
    vk_renderer = *std::move(created);
  }
  // The two renderers' calls, so that the loop below times either.
  struct Renderer {
    std::function<absl::Status(const GaussianStore&)> Upload;
    std::function<absl::Status(const LidarModel&, const LidarSweepPose&, const LidarRenderOptions&,
                               LidarRenderOutput*)>
        Render;
    std::function<absl::Status(const LidarUpstreamGrads&, LidarGaussianGrads*, bool)> Backward;
  } renderer;
  if (vk_renderer) {
    renderer = {[&](const GaussianStore& s) { return vk_renderer->Upload(s); },
                [&](const LidarModel& m, const LidarSweepPose& sw, const LidarRenderOptions& o,
                    LidarRenderOutput* r) { return vk_renderer->Render(m, sw, o, r); },
                [&](const LidarUpstreamGrads& u, LidarGaussianGrads* g, bool det) {
                  return vk_renderer->Backward(u, g, det);
                }};
  } else {
    renderer = {[&](const GaussianStore& s) { return cpu_renderer.Upload(s); },
                [&](const LidarModel& m, const LidarSweepPose& sw, const LidarRenderOptions& o,
                    LidarRenderOutput* r) { return cpu_renderer.Render(m, sw, o, r); },
                [&](const LidarUpstreamGrads& u, LidarGaussianGrads* g, bool det) {
                  return cpu_renderer.Backward(u, g, det);
                }};
  }
  LidarRenderOutput out;
  LidarGaussianGrads grads;
  auto fail = [](const absl::Status& s) {
    std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
    return 1;
  };
  if (absl::Status s = renderer.Upload(store); !s.ok()) return fail(s);
  std::vector<double> t_static, t_rolling, t_rolling_proj, t_static_proj, t_keep, t_backward, t_backward_det;
  size_t rolling_splats = 0, static_splats = 0;
  for (int i = 0; i < repeats + 1; ++i) {
    opt.keep_for_backward = false;
    if (absl::Status s = renderer.Render(model, fixed, opt, &out); !s.ok()) return fail(s);
    const double ts = out.total_ms, tsp = out.projection_ms;
    static_splats = out.num_visible;
    if (absl::Status s = renderer.Render(model, rolling, opt, &out); !s.ok()) return fail(s);
    const double tr = out.total_ms, trp = out.projection_ms;
    rolling_splats = out.num_visible;
    opt.keep_for_backward = true;
    if (absl::Status s = renderer.Render(model, fixed, opt, &out); !s.ok()) return fail(s);
    const double tk = out.total_ms;
    const auto b0 = std::chrono::steady_clock::now();
    if (absl::Status s = renderer.Backward({d_range.data(), d_alpha.data(), d_intensity.data()}, &grads, false); !s.ok()) {
      return fail(s);
    }
    const double tb = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - b0).count();
    const auto b1 = std::chrono::steady_clock::now();
    if (absl::Status s = renderer.Backward({d_range.data(), d_alpha.data(), d_intensity.data()}, &grads, true);
        !s.ok()) {
      return fail(s);
    }
    const double tbd = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - b1).count();
    if (i == 0) continue;  // warm-up
    t_static.push_back(ts);
    t_static_proj.push_back(tsp);
    t_rolling.push_back(tr);
    t_rolling_proj.push_back(trp);
    t_keep.push_back(tk);
    t_backward.push_back(tb);
    t_backward_det.push_back(tbd);
  }
  auto med = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  std::printf("lidar %dx%d (%s, %s), %zu Gaussians, medians over %d repeats:\n", model.beams(), columns,
              kernel.c_str(), vk_renderer ? vk_renderer->device_name().c_str() : LidarRenderer::SimdIsa(), store.size(), repeats);
  std::printf("  static sweep         %7.1f ms (projection %.1f), %zu splats\n", med(t_static), med(t_static_proj),
              static_splats);
  std::printf("  rolling sweep        %7.1f ms (projection %.1f), %zu splats\n", med(t_rolling), med(t_rolling_proj),
              rolling_splats);
  std::printf("  forward, kept        %7.1f ms\n", med(t_keep));
  std::printf("  backward             %7.1f ms\n", med(t_backward));
  std::printf("  backward, determ.    %7.1f ms\n", med(t_backward_det));
  return 0;
}
