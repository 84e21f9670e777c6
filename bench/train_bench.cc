// Training-step speed: one iteration of the static trainer (parameters ->
// device scene, forward with keep_for_backward, L1 + D-SSIM + depth loss and
// gradients, backward, Adam) on procedural street scenes, per stage. Settings
// of the issue: 648x420 with 139k Gaussians (OpenSplat's CPU figure) and
// 1242x375 with 300k. Both backends side by side (issue 4): --backends
// cpu,vulkan. On the vulkan backend the loss and Adam stay on the host (as in
// the trainer), so "upload" and the read-backs inside forward and backward are
// part of the step.
//   train_bench [--settings 648x420x139000,1242x375x300000] [--iters 10] [--sh
//   3] [--deterministic]
//               [--backends cpu,vulkan]
#include <chrono>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "bench/train_bench_scene.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/synthetic_street.h"
#include "scene/train/losses.h"
#include "scene/train/train_state.h"

using namespace streetsim;
using Clock = std::chrono::steady_clock;
static double Ms(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

int main(int argc, char **argv) {
  std::string settings = "648x420x139000,1242x375x300000";
  int iters = 10, sh = 3;
  bool deterministic = false;
  std::string backends = "cpu";
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--settings") && i + 1 < argc)
      settings = argv[++i];
    else if (!std::strcmp(argv[i], "--iters") && i + 1 < argc)
      iters = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--sh") && i + 1 < argc)
      sh = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--deterministic"))
      deterministic = true;
    else if (!std::strcmp(argv[i], "--backends") && i + 1 < argc)
      backends = argv[++i];
    else {
      std::fprintf(stderr, "usage: train_bench [--settings WxHxN,...] [--iters "
                           "N] [--sh D] [--deterministic] "
                           "[--backends cpu,vulkan]\n");
      return 2;
    }
  }
  if (iters < 1) {
    std::fprintf(stderr, "--iters must be >= 1\n");
    return 2;
  }
  ThreadPool pool(0);
  for (const std::string &backend_name :
       std::vector<std::string>(absl::StrSplit(backends, ','))) {
    const absl::StatusOr<Backend> backend = ParseBackend(backend_name);
    if (!backend.ok()) {
      std::fprintf(stderr, "%s\n", backend.status().ToString().c_str());
      return 2;
    }
    auto engine = CreateEngine(*backend);
    if (!engine.ok()) {
      std::printf("backend %s: %s\n", backend_name.c_str(),
                  engine.status().ToString().c_str());
      continue;
    }
    std::printf("backend %s, device: %s%s\n", backend_name.c_str(),
                (*engine)->device_name().c_str(),
                deterministic ? " (deterministic backward)" : "");
    std::printf("%-18s %8s %8s %8s %8s %8s %8s %8s %9s\n", "setting", "upload",
                "forward", "loss", "backward", "adam", "total", "visible",
                "instances");
    for (const std::string &s :
         std::vector<std::string>(absl::StrSplit(settings, ','))) {
      bench::BenchSetting setting;
      if (!bench::ParseBenchSetting(s, &setting)) {
        std::fprintf(stderr, "bad setting %s\n", s.c_str());
        return 2;
      }
      const int w = setting.width, h = setting.height;
      const size_t n = setting.num_gaussians;
      const GaussianStore street =
          MakeSyntheticStreet({.num_gaussians = n, .seed = 3, .sh_degree = sh});
      train::TrainState st = train::TrainState::Init(street, 20.0, 1, 1);
      const PinholeCamera cam = bench::BenchCamera(w, h);
      std::vector<float> d_rgb, d_depth;
      const bench::BenchTarget bt =
          bench::RenderBenchTarget(**engine, street, cam);
      std::unique_ptr<DeviceScene> scene;
      RenderOutput out;
      GaussianGrads grads;
      train::Hyper hyper;
      double t_up = 0, t_fwd = 0, t_loss = 0, t_bwd = 0, t_adam = 0, t_tot = 0;
      double t_proj = 0, t_sort = 0, t_blend = 0,
             t_bblend = 0; // sub-stages of forward / backward
      bool failed = false;
      for (int it = 0; it <= iters && !failed; ++it) {
        const auto t0 = Clock::now();
        auto t = Clock::now();
        (void)(*engine)->UpdateSceneParams(train::ParamsView(st, sh), &scene);
        const double up = Ms(t);
        t = Clock::now();
        RenderOptions ro;
        ro.keep_for_backward = true;
        (void)(*engine)->Render(*scene, cam, ro, &out);
        const double fwd = Ms(t);
        t = Clock::now();
        bench::BenchLoss(pool, out, bt, w, h, &d_rgb, &d_depth);
        const double loss = Ms(t);
        t = Clock::now();
        BackwardOptions bo;
        bo.deterministic = deterministic;
        const absl::Status bs = (*engine)->RenderBackward(
            *scene, {d_rgb.data(), d_depth.data(), nullptr}, bo, &grads);
        if (!bs.ok()) {
          std::printf("%-18s backward: %s\n", s.c_str(), bs.ToString().c_str());
          failed = true;
          continue;
        }
        const double bwd = Ms(t);
        t = Clock::now();
        train::AdamStepGaussians(&st, grads, sh, it + 1, hyper, pool);
        const double adam = Ms(t);
        if (it == 0)
          continue; // warm-up
        t_up += up, t_fwd += fwd, t_loss += loss, t_bwd += bwd, t_adam += adam,
            t_tot += Ms(t0);
        t_proj += out.timings.projection_ms, t_sort += out.timings.sort_ms,
            t_blend += out.timings.blend_ms;
        t_bblend += grads.blend_backward_ms;
      }
      if (failed)
        continue;
      const double k = 1.0 / iters;
      std::printf("%-18s %8.1f %8.1f %8.1f %8.1f %8.1f %8.1f %8zu %9zu   "
                  "ms/iteration\n",
                  s.c_str(), t_up * k, t_fwd * k, t_loss * k, t_bwd * k,
                  t_adam * k, t_tot * k, out.stats.num_visible,
                  out.stats.num_tile_instances);
      std::printf("%-18s forward: projection %.1f, sort+bin %.1f, blend %.1f", "", t_proj * k, t_sort * k,
                  t_blend * k);
      // Only the cpu backend times its backward's stages (GaussianGrads::blend_backward_ms).
      if (t_bblend > 0) {
        std::printf("; backward: blend %.1f, projection %.1f", t_bblend * k, (t_bwd - t_bblend) * k);
      }
      std::printf("\n");
    }
  }
  return 0;
}
