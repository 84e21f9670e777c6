// Training-step speed with S3Gaussian's deformation field vs the static step (issue 5): one
// iteration = [deform: field forward at the view's time] -> upload -> forward with
// keep_for_backward -> L1 + D-SSIM + depth -> backward -> [field: DeformBackward + plane
// regularisers + field Adam] -> Gaussian Adam, on a procedural street scene.
//   train_field_bench [--settings 648x420x139000] [--iters 10] [--field-size spec|small]
//       [--backend cpu|vulkan] [--field-device cpu|vulkan] [--field-optimizer auto|device|host]
// --field-optimizer picks where the Vulkan field's regularisers and Adam run
// (FieldOptions::optimizer; auto: the device on a GPU, the host on lavapipe): the A/B of
// docs/benchmarks.md.
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
#include "scene/field/field_regularizers.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/gradient_guard.h"
#include "scene/train/losses.h"
#include "scene/train/train_state.h"

using namespace streetsim;
using Clock = std::chrono::steady_clock;
static double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

int main(int argc, char** argv) {
  std::string settings = "648x420x139000", size = "spec", backend_name = "cpu", field_device = "cpu",
              optimizer = "auto";
  int iters = 10;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--settings") && i + 1 < argc) settings = argv[++i];
    else if (!std::strcmp(argv[i], "--iters") && i + 1 < argc) iters = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--field-size") && i + 1 < argc) size = argv[++i];
    else if (!std::strcmp(argv[i], "--backend") && i + 1 < argc) backend_name = argv[++i];
    else if (!std::strcmp(argv[i], "--field-device") && i + 1 < argc) field_device = argv[++i];
    else if (!std::strcmp(argv[i], "--field-optimizer") && i + 1 < argc) optimizer = argv[++i];
    else {
      argc = -1;
      break;
    }
  }
  const bool bad = argc < 0 || iters < 1 || (size != "spec" && size != "small") ||
                   (backend_name != "cpu" && backend_name != "vulkan") ||
                   (field_device != "cpu" && field_device != "vulkan") ||
                   !train::ParseFieldOptimizerPlace(optimizer).ok();
  if (bad) {
    std::fprintf(stderr,
                 "usage: train_field_bench [--settings WxHxN,...] [--iters N] [--field-size spec|small] "
                 "[--backend cpu|vulkan] [--field-device cpu|vulkan] [--field-optimizer auto|device|host]\n");
    return 2;
  }
  auto engine = CreateEngine(backend_name == "vulkan" ? Backend::kVulkan : Backend::kCpu);
  if (!engine.ok()) {
    std::fprintf(stderr, "%s\n", engine.status().ToString().c_str());
    return 1;
  }
  std::printf("device: %s, field %s on %s, field optimiser %s\n", (*engine)->device_name().c_str(), size.c_str(),
              field_device.c_str(), field_device == "vulkan" ? optimizer.c_str() : "host");
  std::printf("%-18s %-7s %8s %8s %8s %8s %8s %8s %8s %8s %8s\n", "setting", "mode", "deform", "upload", "forward",
              "loss", "backward", "guard", "field", "adam", "total");
  ThreadPool pool(0);
  constexpr int sh = 3;
  for (const std::string& s : std::vector<std::string>(absl::StrSplit(settings, ','))) {
    bench::BenchSetting setting;
    if (!bench::ParseBenchSetting(s, &setting)) {
      std::fprintf(stderr, "bad setting %s\n", s.c_str());
      return 2;
    }
    const int w = setting.width, h = setting.height;
    const size_t n = setting.num_gaussians;
    const GaussianStore street = MakeSyntheticStreet({.num_gaussians = n, .seed = 3, .sh_degree = sh});
    const PinholeCamera cam = bench::BenchCamera(w, h);
    std::vector<float> d_rgb, d_depth;
    const bench::BenchTarget bt = bench::RenderBenchTarget(**engine, street, cam);
    // Back to back on the same data: static, then with the field (the machine is shared).
    for (const bool with_field : {false, true}) {
      train::TrainState st = train::TrainState::Init(street, 20.0, 1, 1);
      std::unique_ptr<train::DynamicStage> stage;
      if (with_field) {
        train::FieldOptions fo;
        fo.mode = train::FieldMode::kS3Gaussian;
        fo.device = field_device == "vulkan" ? train::FieldDevice::kVulkan : train::FieldDevice::kCpu;
        fo.optimizer = *train::ParseFieldOptimizerPlace(optimizer);  // checked above
        if (size == "small") {
          fo.config.channels = 8;
          fo.config.base_resolution = 16;
          fo.config.multires = {1, 2};
          fo.config.time_resolution = 8;
          fo.config.width = 32;
        }
        auto b = train::DynamicStage::Begin(&st, fo, {0, 1'000'000});
        if (!b.ok()) {
          std::fprintf(stderr, "%s\n", b.status().ToString().c_str());
          return 1;
        }
        stage = std::move(*b);
      }
      std::unique_ptr<DeviceScene> scene;
      RenderOutput out;
      GaussianGrads grads;
      train::Hyper hyper;
      double t_def = 0, t_up = 0, t_fwd = 0, t_loss = 0, t_bwd = 0, t_guard = 0, t_field = 0, t_adam = 0, t_tot = 0;
      for (int it = 0; it <= iters; ++it) {
        const auto t0 = Clock::now();
        auto t = Clock::now();
        GaussianParamsView pv = train::ParamsView(st, sh);
        if (stage) {
          absl::StatusOr<GaussianParamsView> d = stage->Deform(st, sh, 100'000 * (it % 10), pool);
          if (!d.ok()) {
            std::fprintf(stderr, "%s\n", d.status().ToString().c_str());
            return 1;
          }
          pv = *d;
        }
        const double def = Ms(t);
        t = Clock::now();
        (void)(*engine)->UpdateSceneParams(pv, &scene);
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
        (void)(*engine)->RenderBackward(*scene, {d_rgb.data(), d_depth.data(), nullptr}, {}, &grads);
        const double bwd = Ms(t);
        t = Clock::now();
        // The trainer's non-finite gradient check (scene/train/gradient_guard.h), as it runs per step.
        if (absl::Status g = train::GuardGradients(it, st.size(), 0.01, &grads, pool); !g.ok()) {
          std::fprintf(stderr, "%s\n", g.ToString().c_str());
          return 1;
        }
        const double guard = Ms(t);
        t = Clock::now();
        if (stage) {
          if (absl::StatusOr<double> b = stage->Backward(st, sh, it + 1, &grads, pool); !b.ok()) {
            std::fprintf(stderr, "%s\n", b.status().ToString().c_str());
            return 1;
          }
        }
        const double fld = Ms(t);
        t = Clock::now();
        train::AdamStepGaussians(&st, grads, sh, it + 1, hyper, pool);
        const double adam = Ms(t);
        if (it == 0) continue;  // warm-up
        t_def += def, t_up += up, t_fwd += fwd, t_loss += loss, t_bwd += bwd, t_guard += guard, t_field += fld, t_adam += adam;
        t_tot += Ms(t0);
      }
      const double k = 1.0 / iters;
      std::printf("%-18s %-7s %8.1f %8.1f %8.1f %8.1f %8.1f %8.1f %8.1f %8.1f %8.1f   ms/iteration\n", s.c_str(),
                  with_field ? "field" : "static", t_def * k, t_up * k, t_fwd * k, t_loss * k, t_bwd * k,
                  t_guard * k, t_field * k, t_adam * k, t_tot * k);
      if (stage) {
        std::printf("%-18s %s\n", "", stage->timings().Summary().c_str());
        if (absl::Status sync = stage->SyncHost(); !sync.ok()) {
          std::fprintf(stderr, "%s\n", sync.ToString().c_str());
          return 1;
        }
        // The host's parameter-sized passes (what the device optimiser replaces), alone (same
        // pool, 3 repetitions).
        field::DeformationField f = stage->field();
        const field::FieldLayout& L = f.layout();
        std::vector<float> g(L.total, 0.0f);
        field::FieldAdamState a;
        a.Init(L.total);
        double t_zero = 0, t_reg = 0, t_fadam = 0;
        for (int r = 0; r < 3; ++r) {
          auto t = Clock::now();
          std::fill(g.begin(), g.end(), 0.0f);
          t_zero += Ms(t);
          t = Clock::now();
          field::PlaneRegularizers<float>(L, f.params().data(), {}, g.data(), pool);
          t_reg += Ms(t);
          t = Clock::now();
          field::FieldAdamStep(L, f.mutable_params().data(), g.data(), &a, {1e-4, 1e-5}, pool);
          t_fadam += Ms(t);
        }
        std::printf("%-18s field: %zu parameters; of which zero-fill %.1f, regularisers %.1f, field Adam %.1f ms\n",
                    "", L.total, t_zero / 3, t_reg / 3, t_fadam / 3);
      }
    }
  }
  return 0;
}
