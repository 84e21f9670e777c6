// Deformation field on Vulkan (render/vulkan/field/vulkan_field.h, docs/field.md "Vulkan field"):
// forward and backward per timestamp at the spec's sizes (4 levels x 6 planes x 32 channels,
// 64..512, time 25, MLP 128 -> 64 -> {3, 48}) for N Gaussians uniformly random in a
// 200 x 200 x 20 m AABB, random dL/d(Δx, ΔSH). Prints device time (timestamps around each batch's
// kernels, summed) and wall time (the whole call: uploads, kernels, readbacks of Δx / ΔSH or of
// the 136 MiB gradient, and the host-side adds). With --cpu, the cpu field on the same data back
// to back (FieldForward / FieldBackward<float>, --threads threads).
//   field_vk_bench [--sizes 139000,300000,500000] [--repeats 3] [--batch 65536] [--cas] [--cpu]
//                  [--threads 0] [--lavapipe] [--no-warmup] [--check]
// --check: also compares one fresh forward + backward with the cpu float field at every size
// (relative L2 errors of Δx, ΔSH, the field gradient and dL/d(means)): a correctness check at
// sizes where the grids are 2D and the batches many, which the unit tests do not reach.
// Means over --repeats rounds after one warm-up round (buffers, first-use page faults), unless
// --no-warmup (lavapipe: a round at 500k takes minutes).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_eval.h"
#include "render/vulkan/field/vulkan_field.h"

using namespace streetsim;
using namespace streetsim::field;
using Clock = std::chrono::steady_clock;
static double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

int main(int argc, char** argv) {
  std::vector<size_t> sizes = {139000, 300000, 500000};
  int repeats = 3, threads = 0;
  size_t batch = 65536;
  bool cas = false, cpu = false, lavapipe = false, warmup = true, check = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "%s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--sizes") {
      sizes.clear();
      for (const std::string& p : std::vector<std::string>(absl::StrSplit(next(), ',', absl::SkipEmpty()))) {
        size_t n = 0;
        if (!absl::SimpleAtoi(p, &n)) {
          std::fprintf(stderr, "bad size %s\n", p.c_str());
          return 2;
        }
        sizes.push_back(n);
      }
    } else if (a == "--repeats" && absl::SimpleAtoi(next(), &repeats)) {
    } else if (a == "--batch" && absl::SimpleAtoi(next(), &batch)) {
    } else if (a == "--threads" && absl::SimpleAtoi(next(), &threads)) {
    } else if (a == "--cas") {
      cas = true;
    } else if (a == "--cpu") {
      cpu = true;
    } else if (a == "--check") {
      check = true;
    } else if (a == "--no-warmup") {
      warmup = false;
    } else if (a == "--lavapipe") {
      lavapipe = true;
    } else {
      std::fprintf(stderr, "unknown or bad argument %s\n", a.c_str());
      return 2;
    }
  }
  FieldAabb box;
  box.min[0] = -100; box.min[1] = -100; box.min[2] = -5;
  box.max[0] = 100;  box.max[1] = 100;  box.max[2] = 15;
  absl::StatusOr<DeformationField> f = DeformationField::Create(FieldConfig{}, box, {0, 5'000'000}, 1);
  if (!f.ok()) return 1;
  {  // time planes off 1, so that nothing is trivially constant
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<float> u(-0.2f, 0.2f);
    const FieldLayout& L = f->layout();
    for (const PlaneInfo& pi : L.planes) {
      if (!PlaneHasTime(pi.plane)) continue;
      for (size_t i = 0; i < pi.size(L.channels); ++i) f->mutable_params()[pi.offset + i] += u(rng);
    }
  }
  VulkanFieldOptions o;
  o.batch_rows = batch;
  o.force_cas_atomics = cas;
  if (lavapipe) o.device = VulkanDevicePreference::kLavapipe;
  const auto tc = Clock::now();
  auto vf = VulkanField::Create(*f, o);
  if (!vf.ok()) {
    std::fprintf(stderr, "%s\n", std::string(vf.status().message()).c_str());
    return 1;
  }
  std::printf("%s; %d plane buffers, batch %zu, %s; create + upload %.0f ms\n", (*vf)->device_description().c_str(),
              (*vf)->plane_buffers(), (*vf)->batch_rows(),
              (*vf)->uses_float_atomics() ? "float atomics" : "CAS scatter", Ms(tc));
  ThreadPool pool(threads);
  FieldWorkspace ws;
  const FieldQuery q = f->Query(1'700'000);
  std::printf("%9s %-7s %12s %12s %13s %13s\n", "gaussians", "backend", "fwd dev ms", "fwd wall ms", "bwd dev ms",
              "bwd wall ms");
  for (size_t n : sizes) {
    std::mt19937_64 rng(n);
    std::uniform_real_distribution<float> u(0, 1);
    std::normal_distribution<float> g;
    std::vector<float> means(n * 3), gdx(n * 3), gdsh(n * kShOutputs);
    for (size_t i = 0; i < n; ++i)
      for (int k = 0; k < 3; ++k) means[i * 3 + k] = box.min[k] + u(rng) * (box.max[k] - box.min[k]);
    for (float& v : gdx) v = g(rng);
    for (float& v : gdsh) v = g(rng);
    std::vector<float> dx, dsh, d_params(f->layout().total), d_means(n * 3);
    double fd = 0, fw = 0, bd = 0, bw = 0;
    for (int r = warmup ? 0 : 1; r <= repeats; ++r) {  // round 0 warms up (buffers, pages)
      if (!(*vf)->Forward(q, means, &dx, &dsh).ok()) return 1;
      if (!(*vf)->Backward(q, means, gdx, gdsh, d_params, d_means).ok()) return 1;
      if (r == 0) continue;
      fd += (*vf)->last_forward().device_ms;
      fw += (*vf)->last_forward().wall_ms;
      bd += (*vf)->last_backward().device_ms;
      bw += (*vf)->last_backward().wall_ms;
    }
    std::printf("%9zu %-7s %12.1f %12.1f %13.1f %13.1f\n", n, "vulkan", fd / repeats, fw / repeats, bd / repeats,
                bw / repeats);
    if (cpu) {
      std::vector<float> cdx(n * 3), cdsh(n * kShOutputs);
      double cf = 0, cb = 0;
      for (int r = warmup ? 0 : 1; r <= repeats; ++r) {
        const auto t0 = Clock::now();
        FieldForward<float>(f->layout(), f->params().data(), q, means.data(), nullptr, n, cdx.data(), cdsh.data(),
                            pool, ws);
        const double a = Ms(t0);
        const auto t1 = Clock::now();
        FieldBackward<float>(f->layout(), f->params().data(), q, means.data(), n, gdx.data(), gdsh.data(),
                             d_params.data(), d_means.data(), pool, ws);
        if (r > 0) cf += a, cb += Ms(t1);
      }
      std::printf("%9zu %-7s %12s %12.1f %13s %13.1f\n", n, "cpu", "-", cf / repeats, "-", cb / repeats);
    }
    if (check) {
      auto rel = [](const std::vector<float>& ref, const std::vector<float>& x) {
        double num = 0, den = 0;
        for (size_t i = 0; i < ref.size(); ++i) {
          num += (double(ref[i]) - x[i]) * (double(ref[i]) - x[i]);
          den += double(ref[i]) * ref[i];
        }
        return std::sqrt(num / std::max(den, 1e-300));
      };
      const FieldLayout& L = f->layout();
      std::vector<float> cdx(n * 3), cdsh(n * kShOutputs), cgp(L.total, 0.0f), cgm(n * 3, 0.0f);
      std::vector<float> vgp(L.total, 0.0f), vgm(n * 3, 0.0f);
      FieldForward<float>(L, f->params().data(), q, means.data(), nullptr, n, cdx.data(), cdsh.data(), pool, ws);
      FieldBackward<float>(L, f->params().data(), q, means.data(), n, gdx.data(), gdsh.data(), cgp.data(), cgm.data(),
                           pool, ws);
      if (!(*vf)->Forward(q, means, &dx, &dsh).ok()) return 1;
      if (!(*vf)->Backward(q, means, gdx, gdsh, vgp, vgm).ok()) return 1;
      // dL/d(means) is discontinuous across texel edges (the bilinear slope changes): a coordinate
      // within rounding of an edge takes the neighbouring cell's slope on one side. Such rows are
      // few; the error without the worst 0.1 % of rows shows whether anything else differs.
      std::vector<std::pair<double, size_t>> row_err(n);
      for (size_t i = 0; i < n; ++i) {
        double e = 0;
        for (int k = 0; k < 3; ++k) e += (double(cgm[i * 3 + k]) - vgm[i * 3 + k]) * (cgm[i * 3 + k] - vgm[i * 3 + k]);
        row_err[i] = {e, i};
      }
      std::sort(row_err.begin(), row_err.end());
      std::vector<float> cgm_trim, vgm_trim;
      for (size_t j = 0; j < n - n / 1000; ++j) {
        for (int k = 0; k < 3; ++k) {
          cgm_trim.push_back(cgm[row_err[j].second * 3 + k]);
          vgm_trim.push_back(vgm[row_err[j].second * 3 + k]);
        }
      }
      std::printf("%9zu check vs cpu float: dx %.1e  dsh %.1e  d_params %.1e  d_means %.1e (%.1e without the worst "
                  "0.1 %% of rows)\n",
                  n, rel(cdx, dx), rel(cdsh, dsh), rel(cgp, vgp), rel(cgm, vgm), rel(cgm_trim, vgm_trim));
      // Both float gradients against the cpu double one (the reference of the gradient checks).
      const std::vector<double> pd(f->params().begin(), f->params().end()), md(means.begin(), means.end());
      const std::vector<double> gdx_d(gdx.begin(), gdx.end()), gdsh_d(gdsh.begin(), gdsh.end());
      std::vector<double> dgp(L.total, 0.0), dgm(n * 3, 0.0);
      FieldBackward<double>(L, pd.data(), q, md.data(), n, gdx_d.data(), gdsh_d.data(), dgp.data(), dgm.data(), pool,
                            ws);
      const std::vector<float> dgp_f(dgp.begin(), dgp.end());
      std::printf("%9zu d_params vs cpu double: vulkan %.1e, cpu float %.1e\n", n, rel(dgp_f, vgp), rel(dgp_f, cgp));
    }
  }
  return 0;
}
