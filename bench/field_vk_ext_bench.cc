// The extended field on Vulkan (render/vulkan/field/ext/vulkan_extended_field.h, docs/field.md
// "Extended field on Vulkan"): ms per 1000 Gaussians of a forward and of a forward + backward, for
// the rows of field_ext_bench's table (every module off, each module alone, pairs, all), at the
// spec's sizes (K = 5), Gaussians uniformly random in a 200 x 200 x 20 m AABB, random output
// gradients, training pass (ε on). Device time = GPU timestamps around each batch's kernels,
// summed; wall = the whole call (staging, kernels, readbacks, gradient download and host adds).
// With --cpu, the cpu float path (ExtendedForward / ExtendedBackward, --threads threads) on the
// same data right after each Vulkan row (A/B back to back).
//   field_vk_ext_bench [--gaussians 2000] [--repeats 1] [--no-warmup] [--modules LIST] [--batch 65536]
//                      [--cpu] [--threads 1] [--lavapipe]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "bench/field_ext_bench_scene.h"
#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_field.h"
#include "render/vulkan/field/ext/vulkan_extended_field.h"

using namespace streetsim;
using namespace streetsim::field;
using streetsim::bench::CheckOrExit;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

// Mean wall ms of fn over `repeats` runs (after one warm-up unless !warmup); *device: mean of
// what `device_ms` reports after each run.
double Mean(const std::function<void()>& fn, const std::function<double()>& device_ms, int repeats, bool warmup,
            double* device) {
  if (warmup) fn();
  double wall = 0, dev = 0;
  for (int r = 0; r < repeats; ++r) {
    const auto t0 = Clock::now();
    fn();
    wall += Ms(t0);
    dev += device_ms();
  }
  *device = dev / repeats;
  return wall / repeats;
}

}  // namespace

int main(int argc, char** argv) {
  size_t n = 2000, batch = 65536;
  int repeats = 1, threads = 1;
  bool warmup = true, cpu = false, lavapipe = false;
  std::string only;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> const char* {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--gaussians") {
      n = std::strtoul(next(), nullptr, 10);
    } else if (a == "--repeats") {
      repeats = std::max(1, std::atoi(next()));
    } else if (a == "--batch") {
      batch = std::strtoul(next(), nullptr, 10);
    } else if (a == "--threads") {
      threads = std::atoi(next());
    } else if (a == "--modules") {
      only = next();
    } else if (a == "--no-warmup") {
      warmup = false;
    } else if (a == "--cpu") {
      cpu = true;
    } else if (a == "--lavapipe") {
      lavapipe = true;
    } else {
      std::fprintf(stderr, "unknown flag %s\n", a.c_str());
      return 2;
    }
  }
  bench::ExtBenchScene s = bench::MakeExtBenchScene(n);
  ThreadPool pool(threads);
  VulkanFieldOptions vo;
  vo.batch_rows = batch;
  if (lavapipe) vo.device = VulkanDevicePreference::kLavapipe;
  const double per = 1000.0 / n;
  bool printed_header = false;
  for (const char* modules : bench::kExtBenchRows) {
    if (!only.empty() && only != modules) continue;
    bench::ExtBenchRow r = bench::MakeExtBenchRow(s, modules);
    const ExtendedFieldConfig& ec = r.field.config();
    r.pass.noise_seed = 7;
    absl::StatusOr<std::unique_ptr<VulkanExtendedField>> vf = VulkanExtendedField::Create(r.field, vo);
    CheckOrExit(vf.status());
    if (!printed_header) {
      std::printf("field_vk_ext_bench: %zu Gaussians, spec sizes, K = %d with temporal, %s, batch %zu, %d plane "
                  "buffer(s), %s atomics; ms per 1000 Gaussians (mean of %d%s)\n",
                  n, ec.temporal ? ec.tokens() : 2 * ec.window_k + 1, (*vf)->device_description().c_str(),
                  (*vf)->batch_rows(), (*vf)->plane_buffers(), (*vf)->uses_float_atomics() ? "float" : "CAS",
                  repeats, warmup ? " after a warm-up" : ", no warm-up");
      std::printf("| field | vk fwd device | vk fwd wall | vk fwd+bwd device | vk fwd+bwd wall |%s\n",
                  cpu ? " cpu fwd wall | cpu fwd+bwd wall |" : "");
      std::printf("|---|---|---|---|---|%s\n", cpu ? "---|---|" : "");
      printed_header = true;
    }
    VulkanExtendedField& v = **vf;
    double fdev = 0, fbdev = 0;
    const double fwall = Mean([&] { CheckOrExit(v.Forward(r.pass, r.in, r.out).status()); },
                              [&] { return v.last_forward().device_ms; }, repeats, warmup, &fdev);
    const double fbwall = Mean(
        [&] {
          CheckOrExit(v.Forward(r.pass, r.in, r.out).status());
          CheckOrExit(v.Backward(r.pass, r.in, r.g, 1e-4 / n, r.gi).status());
        },
        [&] { return v.last_forward().device_ms + v.last_backward().device_ms; }, repeats, warmup, &fbdev);
    std::printf("| %s | %.1f | %.1f | %.1f | %.1f |", ec.ModulesString().c_str(), fdev * per, fwall * per,
                fbdev * per, fbwall * per);
    if (cpu) {
      const ExtModel<float> model = ModelOf(r.field);
      ExtWorkspace ws;
      double unused = 0;
      const double cf =
          Mean([&] { CheckOrExit(ExtendedForward<float>(model, r.pass, r.in, r.out, pool, ws).status()); },
               [] { return 0.0; }, repeats, warmup, &unused);
      const double cfb = Mean(
          [&] {
            CheckOrExit(ExtendedForward<float>(model, r.pass, r.in, r.out, pool, ws).status());
            CheckOrExit(ExtendedBackward<float>(model, r.pass, r.in, r.g, 1e-4 / n, r.gi, pool, ws).status());
          },
          [] { return 0.0; }, repeats, warmup, &unused);
      std::printf(" %.1f | %.1f |", cf * per, cfb * per);
    }
    std::printf("\n");
    std::fflush(stdout);
  }
  return 0;
}
