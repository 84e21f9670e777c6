// Forward-render benchmark: both backends side by side on street-like scenes.
//
//   render_bench [--sizes 100000,500000,1000000] [--backends cpu,vulkan] [--width 1242]
//                [--height 375] [--frames 15] [--warmup 3] [--sh-degree 3]
//
// Each (backend, size) runs in its own child process so that the peak resident memory it reports
// (VmHWM) belongs to that configuration alone. The scene upload is excluded from the timings;
// each frame is rendered from a camera further down the street (median over the frames).
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/engine.h"
#include "scene/gaussians/synthetic_street.h"

namespace streetsim {
namespace {

struct Config {
  std::vector<size_t> sizes = {100'000, 500'000, 1'000'000};
  std::vector<std::string> backends = {"cpu", "vulkan"};
  int width = 1242, height = 375, frames = 15, warmup = 3, sh_degree = 3;
};

struct Result {
  bool ok = false;
  char error[256] = {};
  char device[128] = {};
  double projection_ms = 0, sort_ms = 0, blend_ms = 0, total_ms = 0;
  double visible = 0, instances = 0;
  double peak_rss_mb = 0;
};

double PeakRssMb() {
  std::ifstream f("/proc/self/status");
  std::string line;
  while (std::getline(f, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;
  }
  return 0;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

Result RunOne(const Config& cfg, const std::string& backend_name, size_t n) {
  Result r;
  auto fail = [&](const std::string& msg) {
    std::snprintf(r.error, sizeof(r.error), "%s", msg.c_str());
    return r;
  };
  absl::StatusOr<Backend> backend = ParseBackend(backend_name);
  if (!backend.ok()) return fail(std::string(backend.status().message()));
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(*backend);
  if (!engine.ok()) return fail(std::string(engine.status().message()));
  std::snprintf(r.device, sizeof(r.device), "%s", (*engine)->device_name().c_str());
  const GaussianStore store =
      MakeSyntheticStreet({.num_gaussians = n, .seed = 42, .sh_degree = cfg.sh_degree});
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(store);
  if (!scene.ok()) return fail(std::string(scene.status().message()));

  PinholeCamera cam;
  cam.width = cfg.width;
  cam.height = cfg.height;
  cam.fx = cam.fy = 721.5377 * cfg.width / 1242.0;
  cam.cx = 609.5593 * cfg.width / 1242.0;
  cam.cy = 172.854 * cfg.height / 375.0;
  std::vector<double> proj, sort, blend, total, vis, inst;
  RenderOutput out;
  for (int f = 0; f < cfg.warmup + cfg.frames; ++f) {
    cam.T_world_from_cam = StreetCameraPose(5.0 * (f % 10), 0.5 * (f % 3 - 1));
    if (absl::Status s = (*engine)->Render(**scene, cam, {}, &out); !s.ok()) {
      return fail(std::string(s.message()));
    }
    if (f < cfg.warmup) continue;
    proj.push_back(out.timings.projection_ms);
    sort.push_back(out.timings.sort_ms);
    blend.push_back(out.timings.blend_ms);
    total.push_back(out.timings.total_ms);
    vis.push_back(out.stats.num_visible);
    inst.push_back(out.stats.num_tile_instances);
  }
  r.ok = true;
  r.projection_ms = Median(proj);
  r.sort_ms = Median(sort);
  r.blend_ms = Median(blend);
  r.total_ms = Median(total);
  r.visible = Median(vis);
  r.instances = Median(inst);
  r.peak_rss_mb = PeakRssMb();
  return r;
}

Result RunIsolated(const Config& cfg, const std::string& backend, size_t n) {
  int fds[2];
  if (pipe(fds) != 0) return RunOne(cfg, backend, n);
  const pid_t pid = fork();
  if (pid == 0) {
    close(fds[0]);
    const Result r = RunOne(cfg, backend, n);
    ssize_t ignored = write(fds[1], &r, sizeof(r));
    (void)ignored;
    _exit(0);
  }
  close(fds[1]);
  Result r;
  const ssize_t got = read(fds[0], &r, sizeof(r));
  close(fds[0]);
  int status = 0;
  waitpid(pid, &status, 0);
  if (got != static_cast<ssize_t>(sizeof(r))) {
    r = Result{};
    std::snprintf(r.error, sizeof(r.error), "child process died (status %d)", status);
  }
  return r;
}

bool ParseArgs(int argc, char** argv, Config* cfg) {
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const char* v = i + 1 < argc ? argv[i + 1] : nullptr;
    auto take_int = [&](int* out) { return v && absl::SimpleAtoi(v, out) && ++i; };
    if (a == "--sizes" && v) {
      cfg->sizes.clear();
      for (absl::string_view s : absl::StrSplit(v, ',')) {
        size_t n;
        if (!absl::SimpleAtoi(s, &n)) return false;
        cfg->sizes.push_back(n);
      }
      ++i;
    } else if (a == "--backends" && v) {
      cfg->backends = absl::StrSplit(v, ',');
      ++i;
    } else if (a == "--width") { if (!take_int(&cfg->width)) return false;
    } else if (a == "--height") { if (!take_int(&cfg->height)) return false;
    } else if (a == "--frames") { if (!take_int(&cfg->frames)) return false;
    } else if (a == "--warmup") { if (!take_int(&cfg->warmup)) return false;
    } else if (a == "--sh-degree") { if (!take_int(&cfg->sh_degree)) return false;
    } else {
      return false;
    }
  }
  return cfg->frames > 0 && cfg->warmup >= 0;
}

}  // namespace
}  // namespace streetsim

int main(int argc, char** argv) {
  using namespace streetsim;
  Config cfg;
  if (!ParseArgs(argc, argv, &cfg)) {
    std::fprintf(stderr,
                 "usage: render_bench [--sizes N,N] [--backends cpu,vulkan] [--width W] "
                 "[--height H] [--frames F] [--warmup W] [--sh-degree D]\n");
    return 2;
  }
  std::printf("streetsim render_bench: %dx%d, SH degree %d, median of %d frames after %d warm-up\n",
              cfg.width, cfg.height, cfg.sh_degree, cfg.frames, cfg.warmup);
  std::printf("| backend | device | Gaussians | visible | tile instances | projection ms | sort ms | blend ms | total ms | peak RSS MiB |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|\n");
  bool all_ok = true;
  for (size_t n : cfg.sizes) {
    for (const std::string& b : cfg.backends) {
      const Result r = RunIsolated(cfg, b, n);
      if (!r.ok) {
        std::printf("| %s | - | %zu | error: %s |\n", b.c_str(), n, r.error);
        all_ok = false;
        continue;
      }
      std::printf("| %s | %s | %zu | %.0f | %.0f | %.1f | %.1f | %.1f | %.1f | %.0f |\n", b.c_str(),
                  r.device, n, r.visible, r.instances, r.projection_ms, r.sort_ms, r.blend_ms,
                  r.total_ms, r.peak_rss_mb);
      std::fflush(stdout);
    }
  }
  return all_ok ? 0 : 1;
}
