// The extended field on Vulkan (scene/field/vulkan/ext/vulkan_extended_field.h, docs/field.md
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

#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/vulkan/ext/vulkan_extended_field.h"

using namespace streetsim;
using namespace streetsim::field;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

void Check(const absl::Status& s) {
  if (!s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
    std::exit(1);
  }
}

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
  FieldAabb aabb;
  aabb.min[0] = -100, aabb.min[1] = -100, aabb.min[2] = -5;
  aabb.max[0] = 100, aabb.max[1] = 100, aabb.max[2] = 15;
  const FieldConfig bc;
  absl::StatusOr<DeformationField> base = DeformationField::Create(bc, aabb, {0, 5000000}, 1);
  Check(base.status());
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<float> u(-0.2f, 0.2f);
  for (const PlaneInfo& p : base->layout().planes) {
    if (!PlaneHasTime(p.plane)) continue;
    for (size_t i = 0; i < p.size(bc.channels); ++i) base->mutable_params()[p.offset + i] += u(rng);
  }
  std::vector<float> means(n * 3), opacity(n), scales(n * 3), rotations(n * 4);
  for (size_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) {
      means[i * 3 + a] = std::uniform_real_distribution<float>(aabb.min[a], aabb.max[a])(rng);
      scales[i * 3 + a] = std::uniform_real_distribution<float>(-3, 0)(rng);
    }
    opacity[i] = u(rng) * 10;
    for (int a = 0; a < 4; ++a) rotations[i * 4 + a] = std::normal_distribution<float>()(rng);
  }
  std::vector<float> dx(n * 3), dsh(n * kShOutputs), ds(n * 3), dr(n * 4), dop(n);
  std::vector<float> gdx(n * 3), gdsh(n * kShOutputs), gds(n * 3), gdr(n * 4), gdop(n);
  for (auto* v : {&gdx, &gdsh, &gds, &gdr, &gdop})
    for (float& x : *v) x = u(rng);
  std::vector<float> d_base(base->layout().total), d_means(n * 3), d_op(n), d_sc(n * 3), d_rot(n * 4), d_ext;
  ThreadPool pool(threads);
  VulkanFieldOptions vo;
  vo.batch_rows = batch;
  if (lavapipe) vo.device = VulkanDevicePreference::kLavapipe;
  const double per = 1000.0 / n;
  bool printed_header = false;
  for (const char* modules : {"none", "encoder", "vae", "vae_dilated", "temporal", "attention", "gru", "decoder",
                              "temporal,attention", "temporal,gru", "all", "all,vae_dilated"}) {
    if (!only.empty() && only != modules) continue;
    absl::StatusOr<ExtendedFieldConfig> ec = ExtendedFieldConfig::WithModules(modules);
    Check(ec.status());
    ec->window_dt = 0.02;
    absl::StatusOr<ExtendedField> ef = ExtendedField::Create(*base, *ec, 3);
    Check(ef.status());
    absl::StatusOr<std::unique_ptr<VulkanExtendedField>> vf = VulkanExtendedField::Create(*ef, vo);
    Check(vf.status());
    if (!printed_header) {
      std::printf("field_vk_ext_bench: %zu Gaussians, spec sizes, K = %d with temporal, %s, batch %zu, %d plane "
                  "buffer(s), %s atomics; ms per 1000 Gaussians (mean of %d%s)\n",
                  n, ec->temporal ? ec->tokens() : 2 * ec->window_k + 1, (*vf)->device_description().c_str(),
                  (*vf)->batch_rows(), (*vf)->plane_buffers(), (*vf)->uses_float_atomics() ? "float" : "CAS",
                  repeats, warmup ? " after a warm-up" : ", no warm-up");
      std::printf("| field | vk fwd device | vk fwd wall | vk fwd+bwd device | vk fwd+bwd wall |%s\n",
                  cpu ? " cpu fwd wall | cpu fwd+bwd wall |" : "");
      std::printf("|---|---|---|---|---|%s\n", cpu ? "---|---|" : "");
      printed_header = true;
    }
    ExtPass pass;
    pass.time_coord = ef->base().TimeCoordinate(2500000);
    pass.training = true;
    pass.noise_seed = 7;
    const ExtInputs<float> in{n, means.data(), opacity.data(), scales.data(), rotations.data()};
    const bool dec = ec->decoder;
    const ExtOutputs<float> out{dx.data(), dsh.data(), dec ? ds.data() : nullptr, dec ? dr.data() : nullptr,
                                dec ? dop.data() : nullptr};
    const ExtOutputGrads<float> g{gdx.data(), gdsh.data(), gds.data(), gdr.data(), gdop.data()};
    d_ext.assign(ef->layout().total(), 0.0f);
    const ExtInputGrads<float> gi{d_base.data(), d_ext.data(), d_means.data(), d_op.data(), d_sc.data(), d_rot.data()};
    VulkanExtendedField& v = **vf;
    double fdev = 0, fbdev = 0;
    const double fwall =
        Mean([&] { Check(v.Forward(pass, in, out).status()); }, [&] { return v.last_forward().device_ms; }, repeats,
             warmup, &fdev);
    const double fbwall = Mean(
        [&] {
          Check(v.Forward(pass, in, out).status());
          Check(v.Backward(pass, in, g, 1e-4 / n, gi).status());
        },
        [&] { return v.last_forward().device_ms + v.last_backward().device_ms; }, repeats, warmup, &fbdev);
    std::printf("| %s | %.1f | %.1f | %.1f | %.1f |", ec->ModulesString().c_str(), fdev * per, fwall * per,
                fbdev * per, fbwall * per);
    if (cpu) {
      const ExtModel<float> model = ModelOf(*ef);
      ExtWorkspace ws;
      double unused = 0;
      const double cf = Mean([&] { Check(ExtendedForward<float>(model, pass, in, out, pool, ws).status()); },
                             [] { return 0.0; }, repeats, warmup, &unused);
      const double cfb = Mean(
          [&] {
            Check(ExtendedForward<float>(model, pass, in, out, pool, ws).status());
            Check(ExtendedBackward<float>(model, pass, in, g, 1e-4 / n, gi, pool, ws).status());
          },
          [] { return 0.0; }, repeats, warmup, &unused);
      std::printf(" %.1f | %.1f |", cf * per, cfb * per);
    }
    std::printf("\n");
    std::fflush(stdout);
  }
  return 0;
}
