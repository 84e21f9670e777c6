// Speed of the extended field (scene/field/extended, docs/field.md "Extended field") against
// S3Gaussian's field at the spec's sizes: forward and forward + backward per 1000 Gaussians, CPU
// time on one thread (the machine is shared: wall times are not steady), for S3Gaussian's
// FieldForward / FieldBackward, the extended field with every module off (the ablation baseline),
// each module alone, and all modules; plus the forward multiply-adds and plane samples per
// Gaussian. Gaussians uniformly random in a 200 x 200 x 20 m AABB, time planes varied.
//   field_ext_bench [--gaussians 20000] [--repeats 3] [--k 2] [--modules LIST] (only that row, after S3Gaussian's)
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "bench/field_ext_bench_scene.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/field_eval.h"

using namespace streetsim;
using namespace streetsim::field;
using streetsim::bench::CheckOrExit;

namespace {

double CpuMs() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

double Mean(const std::function<void()>& fn, int repeats) {
  fn();  // warm-up
  double total = 0;
  for (int r = 0; r < repeats; ++r) {
    const double t0 = CpuMs();
    fn();
    total += CpuMs() - t0;
  }
  return total / repeats;
}

}  // namespace

int main(int argc, char** argv) {
  size_t n = 20000;
  int repeats = 3, k = 2;
  std::string only;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (!std::strcmp(argv[i], "--modules")) only = argv[i + 1];
    if (!std::strcmp(argv[i], "--gaussians")) n = std::strtoul(argv[i + 1], nullptr, 10);
    if (!std::strcmp(argv[i], "--repeats")) repeats = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--k")) k = std::atoi(argv[i + 1]);
  }
  bench::ExtBenchScene s = bench::MakeExtBenchScene(n);
  const DeformationField* base = &s.base;
  ThreadPool pool(1);
  const double per = 1000.0 / n;
  const int64_t base_macs = BaseMlpMacs(base->layout());
  std::printf("field_ext_bench: %zu Gaussians, spec sizes (planes %zu, S3Gaussian MLP %zu parameters), one thread,"
              " CPU ms per 1000 Gaussians (mean of %d after a warm-up), K = %d with temporal\n",
              n, base->layout().grid_size, base->layout().total - base->layout().grid_size, repeats, 2 * k + 1);
  std::printf("| field | ext. parameters | MAC / Gaussian | x S3Gaussian | plane samples | forward | fwd + bwd |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  {
    FieldWorkspace ws;
    const FieldQuery q = base->Query(2500000);
    const double f = Mean([&] {
      FieldForward<float>(base->layout(), base->params().data(), q, s.means.data(), nullptr, n, s.dx.data(),
                          s.dsh.data(), pool, ws);
    }, repeats);
    const double fb = Mean([&] {
      FieldForward<float>(base->layout(), base->params().data(), q, s.means.data(), nullptr, n, s.dx.data(),
                          s.dsh.data(), pool, ws);
      FieldBackward<float>(base->layout(), base->params().data(), q, s.means.data(), n, s.gdx.data(), s.gdsh.data(),
                           s.d_base.data(), s.d_means.data(), pool, ws);
    }, repeats);
    std::printf("| S3Gaussian (FieldForward / FieldBackward) | 0 | %lld | 1.0 | 24 | %.1f | %.1f |\n",
                static_cast<long long>(base_macs), f * per, fb * per);
  }
  for (const char* modules : bench::kExtBenchRows) {
    if (!only.empty() && only != modules) continue;
    const bench::ExtBenchRow r = bench::MakeExtBenchRow(s, modules, k);
    const ExtendedFieldConfig& ec = r.field.config();
    const ExtModel<float> model = ModelOf(r.field);
    ExtWorkspace ws;
    const double f = Mean([&] { CheckOrExit(ExtendedForward<float>(model, r.pass, r.in, r.out, pool, ws).status()); },
                          repeats);
    const double fb = Mean([&] {
      CheckOrExit(ExtendedForward<float>(model, r.pass, r.in, r.out, pool, ws).status());
      CheckOrExit(ExtendedBackward<float>(model, r.pass, r.in, r.g, 1e-4 / n, r.gi, pool, ws).status());
    }, repeats);
    const int64_t macs = base_macs + r.field.layout().Macs(ec);
    const int samples = base->config().num_levels() * (3 + 3 * ec.tokens() + (ec.vae && ec.vae_dilation > 0 ? 12 : 0));
    std::printf("| extended: %s | %zu | %lld | %.1f | %d | %.1f | %.1f |\n", ec.ModulesString().c_str(),
                r.field.layout().total(), static_cast<long long>(macs), static_cast<double>(macs) / base_macs, samples,
                f * per, fb * per);
  }
  return 0;
}
