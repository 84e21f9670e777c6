// ms of the camera backward pass (Engine::RenderBackward) in its default and its deterministic
// mode, on the synthetic street (SH 3) seen by a KITTI-like camera.
//   render_backward_bench [--sizes 139000] [--backends cpu,vulkan] [--width 648] [--height 420]
//                         [--repeats 5]
// vulkan: lavapipe unless STREETSIM_VK_DEVICE names another device. Per repeat, back to back on
// the same uploaded scene: a forward with keep_for_backward, the default backward, the
// deterministic backward (alternating which goes first), so both see the same machine load.
// Medians of the repeats after one warm-up; fixed pseudo-random dL/d(rgb, depth, alpha).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "render/engine.h"
#include "scene/gaussians/synthetic_street.h"

namespace {

using namespace streetsim;

struct Config {
  std::vector<size_t> sizes{139000};
  std::vector<std::string> backends{"cpu", "vulkan"};
  int width = 648, height = 420, repeats = 5;
};

template <typename T>
std::vector<T> SplitList(const std::string& s) {
  std::vector<T> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    std::stringstream is(item);
    T v{};
    is >> v;
    out.push_back(v);
  }
  return out;
}

bool ParseArgs(int argc, char** argv, Config* cfg) {
  for (int i = 1; i < argc; i += 2) {
    const std::string a = argv[i];
    if (i + 1 >= argc) return false;
    const std::string v = argv[i + 1];
    if (a == "--sizes") {
      cfg->sizes = SplitList<size_t>(v);
    } else if (a == "--backends") {
      cfg->backends = SplitList<std::string>(v);
    } else if (a == "--width") {
      cfg->width = std::atoi(v.c_str());
    } else if (a == "--height") {
      cfg->height = std::atoi(v.c_str());
    } else if (a == "--repeats") {
      cfg->repeats = std::atoi(v.c_str());
    } else {
      return false;
    }
  }
  return cfg->width > 0 && cfg->height > 0 && cfg->repeats > 0 && !cfg->sizes.empty();
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  Config cfg;
  if (!ParseArgs(argc, argv, &cfg)) {
    std::fprintf(stderr,
                 "usage: render_backward_bench [--sizes N,N] [--backends cpu,vulkan] [--width W] "
                 "[--height H] [--repeats R]\n");
    return 2;
  }
  PinholeCamera cam;
  cam.width = cfg.width;
  cam.height = cfg.height;
  cam.fx = cam.fy = 721.5377 * cfg.width / 1242.0;
  cam.cx = (cfg.width - 1) / 2.0;
  cam.cy = (cfg.height - 1) / 2.0;
  cam.T_world_from_cam = StreetCameraPose(10.0);
  const size_t pixels = size_t{static_cast<size_t>(cfg.width)} * cfg.height;
  std::mt19937 rng(1);
  std::uniform_real_distribution<float> u(-1, 1);
  std::vector<float> g_rgb(pixels * 3), g_depth(pixels), g_alpha(pixels);
  for (float& v : g_rgb) v = u(rng) * 1e-3f;
  for (float& v : g_depth) v = u(rng) * 1e-4f;
  for (float& v : g_alpha) v = u(rng) * 1e-3f;
  const RenderOutputGrads grads{g_rgb.data(), g_depth.data(), g_alpha.data()};

  std::printf("%dx%d, SH 3, %d repeats (medians)\n\n", cfg.width, cfg.height, cfg.repeats);
  std::printf("| backend | Gaussians | visible | tile instances | forward ms | backward ms | "
              "deterministic ms | ratio |\n");
  std::printf("|---|---|---|---|---|---|---|---|\n");
  for (const std::string& name : cfg.backends) {
    if (name != "cpu" && name != "vulkan") {
      std::fprintf(stderr, "backends are cpu and vulkan, not %s\n", name.c_str());
      return 2;
    }
    absl::StatusOr<std::unique_ptr<Engine>> engine =
        CreateEngine(name == "cpu" ? Backend::kCpu : Backend::kVulkan);
    if (!engine.ok()) {
      std::fprintf(stderr, "%s: %s\n", name.c_str(), std::string(engine.status().message()).c_str());
      return 1;
    }
    for (size_t n : cfg.sizes) {
      const GaussianStore store = MakeSyntheticStreet({.num_gaussians = n, .seed = 3, .sh_degree = 3});
      auto scene = (*engine)->Upload(store);
      if (!scene.ok()) {
        std::fprintf(stderr, "%s\n", std::string(scene.status().message()).c_str());
        return 1;
      }
      RenderOptions opt;
      opt.keep_for_backward = true;
      std::vector<double> fwd, fast, det;
      RenderOutput out;
      for (int r = 0; r <= cfg.repeats; ++r) {
        double ms[2] = {0, 0};
        for (int k = 0; k < 2; ++k) {
          const bool deterministic = (k + r) % 2 == 1;
          absl::Status s = (*engine)->Render(**scene, cam, opt, &out);
          GaussianGrads g;
          if (s.ok()) s = (*engine)->RenderBackward(**scene, grads, {.deterministic = deterministic}, &g);
          if (!s.ok()) {
            std::fprintf(stderr, "%s\n", std::string(s.message()).c_str());
            return 1;
          }
          ms[deterministic ? 1 : 0] = g.backward_ms;
          if (r > 0 && k == 0) fwd.push_back(out.timings.total_ms);
        }
        if (r > 0) {  // r == 0 warms up
          fast.push_back(ms[0]);
          det.push_back(ms[1]);
        }
      }
      std::printf("| %s | %zu | %zu | %zu | %.1f | %.1f | %.1f | %.2f |\n",
                  (*engine)->device_name().c_str(), n, out.stats.num_visible,
                  out.stats.num_tile_instances, Median(fwd), Median(fast), Median(det),
                  Median(det) / std::max(Median(fast), 1e-9));
    }
  }
  return 0;
}
