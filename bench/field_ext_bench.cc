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

#include "scene/field/extended/extended_field.h"
#include "scene/field/field_eval.h"

using namespace streetsim;
using namespace streetsim::field;

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

void Check(const absl::Status& s) {
  if (!s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
    std::exit(1);
  }
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
      FieldForward<float>(base->layout(), base->params().data(), q, means.data(), nullptr, n, dx.data(), dsh.data(),
                          pool, ws);
    }, repeats);
    const double fb = Mean([&] {
      FieldForward<float>(base->layout(), base->params().data(), q, means.data(), nullptr, n, dx.data(), dsh.data(),
                          pool, ws);
      FieldBackward<float>(base->layout(), base->params().data(), q, means.data(), n, gdx.data(), gdsh.data(),
                           d_base.data(), d_means.data(), pool, ws);
    }, repeats);
    std::printf("| S3Gaussian (FieldForward / FieldBackward) | 0 | %lld | 1.0 | 24 | %.1f | %.1f |\n",
                static_cast<long long>(base_macs), f * per, fb * per);
  }
  for (const char* modules : {"none", "encoder", "vae", "vae_dilated", "temporal", "attention", "gru", "decoder",
                              "temporal,attention", "temporal,gru", "all", "all,vae_dilated"}) {
    if (!only.empty() && only != modules) continue;
    absl::StatusOr<ExtendedFieldConfig> ec = ExtendedFieldConfig::WithModules(modules);
    Check(ec.status());
    ec->window_k = k;
    ec->window_dt = 0.02;
    absl::StatusOr<ExtendedField> ef = ExtendedField::Create(*base, *ec, 3);
    Check(ef.status());
    const ExtModel<float> model = ModelOf(*ef);
    ExtPass pass;
    pass.time_coord = ef->base().TimeCoordinate(2500000);
    pass.training = true;
    const ExtInputs<float> in{n, means.data(), opacity.data(), scales.data(), rotations.data()};
    const bool dec = ec->decoder;
    const ExtOutputs<float> out{dx.data(), dsh.data(), dec ? ds.data() : nullptr, dec ? dr.data() : nullptr,
                                dec ? dop.data() : nullptr};
    const ExtOutputGrads<float> g{gdx.data(), gdsh.data(), gds.data(), gdr.data(), gdop.data()};
    d_ext.assign(ef->layout().total(), 0.0f);
    const ExtInputGrads<float> gi{d_base.data(), d_ext.data(), d_means.data(), d_op.data(), d_sc.data(), d_rot.data()};
    ExtWorkspace ws;
    const double f = Mean([&] { Check(ExtendedForward<float>(model, pass, in, out, pool, ws).status()); }, repeats);
    const double fb = Mean([&] {
      Check(ExtendedForward<float>(model, pass, in, out, pool, ws).status());
      Check(ExtendedBackward<float>(model, pass, in, g, 1e-4 / n, gi, pool, ws).status());
    }, repeats);
    const int64_t macs = base_macs + ef->layout().Macs(*ec);
    const int samples = bc.num_levels() * (3 + 3 * ec->tokens() + (ec->vae && ec->vae_dilation > 0 ? 12 : 0));
    std::printf("| extended: %s | %zu | %lld | %.1f | %d | %.1f | %.1f |\n", ec->ModulesString().c_str(),
                ef->layout().total(), static_cast<long long>(macs), static_cast<double>(macs) / base_macs, samples,
                f * per, fb * per);
  }
  return 0;
}
