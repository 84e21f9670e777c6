// Deformation-field speed (docs/field.md), spec sizes (4 levels x 6 planes x 32 channels, 64..512,
// time 25, MLP 128 -> 64 -> {3, 48}):
// - serving: field evaluation per timestamp for N Gaussians uniformly random in a 200 x 200 x 20 m
//   AABB, without and with the static skip, and the serving form fitted to it (row "form"; the
//   next row: the form written into the cpu engine's planes, against the host form plus the
//   engine's row update, and the LiDAR's geometry-only evaluation). The field is the spec's init with the space-time
//   planes varied in time over a band of x (--dynamic-fraction of the AABB's x extent), so the
//   Gaussians in the band move and the others do not. Then the same with the extended field
//   (--ext-modules, ';'-separated module lists, default "all"; "" skips these rows): its gate
//   opened (0.1) and its decoder's last layers drawn (Xavier x 0.1), both of which start at 0.
// - training: DeformScene + DeformBackward (random dL/d(deformed means, SH)), the plane
//   regularisers and the field's Adam step, for Gaussians of the procedural street; with
//   --train-ply SCENE.ply also for a trained scene's Gaussians (SH degree 3), once in the file's
//   row order (the trainer's) and once in the field's Morton order.
//   field_bench [--serve 500000] [--train 139000,300000] [--repeats 5] [--samples 50]
//               [--dynamic-fraction 0.1] [--threads 0] [--row-order (no Morton order when serving)]
//               [--ext-modules "all;encoder,vae,attention,gru,decoder"] [--serve-vulkan]
//               [--train-ply SCENE.ply]
//   --serve-vulkan adds serving rows with the field on Vulkan (the server's --field-device vulkan,
//   render/vulkan/field/vulkan_serving.h; a GPU when there is one, else lavapipe, which is slower
//   than the cpu for the field; their first (warm-up) timestamp creates the device field), and the
//   serving form's kernel on a Vulkan engine (row "form kernel": --backend vulkan, the form
//   written into the engine's scene, against the host form plus a whole-scene upload).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <random>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/extended/extended_serving.h"
#include "scene/field/field_regularizers.h"
#include "scene/field/host_planes_writer.h"
#include "scene/field/serving_form.h"
#include "render/params_view.h"
#include "render/vulkan/field/vulkan_serving_form.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/spatial_order.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/ply_io.h"
#include "render/vulkan/field/vulkan_serving.h"
#include "scene/gaussians/synthetic_street.h"

using namespace streetsim;
using namespace streetsim::field;
using Clock = std::chrono::steady_clock;
static double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }
// Process CPU time (all threads), ms: on a machine shared with other jobs wall time varies with
// their load, CPU time much less.
static double CpuMs() {
  timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

namespace {

std::vector<size_t> ParseSizes(const std::string& s) {
  std::vector<size_t> out;
  for (const std::string& p : std::vector<std::string>(absl::StrSplit(s, ',', absl::SkipEmpty()))) {
    size_t n = 0;
    if (!absl::SimpleAtoi(p, &n)) {
      std::fprintf(stderr, "bad size %s\n", p.c_str());
      std::exit(2);
    }
    out.push_back(n);
  }
  return out;
}

// Space-time planes vary in time over the texel columns (x) of a band: the field moves what lies
// in that band of x only.
void MakeBandDynamic(DeformationField* f, double fraction) {
  const FieldLayout& L = f->layout();
  std::vector<float>& p = f->mutable_params();
  for (const PlaneInfo& pi : L.planes) {
    if (pi.plane != 2) continue;  // xt
    const int u0 = static_cast<int>(pi.width * 0.45), u1 = u0 + std::max(1, static_cast<int>(pi.width * fraction));
    for (int v = 0; v < pi.height; ++v)
      for (int u = u0; u < std::min(u1, pi.width); ++u)
        for (int k = 0; k < L.channels; ++k)
          p[pi.offset + (static_cast<size_t>(v) * pi.width + u) * L.channels + k] =
              1.0f + 0.5f * std::sin(6.28318f * (v / float(pi.height - 1)) * (1 + k % 3));
  }
}

GaussianStore RandomInBox(size_t n, const FieldAabb& box, uint64_t seed) {
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n);
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> u(0, 1), s(-0.1f, 0.1f);
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) g.means[i * 3 + k] = box.min[k] + u(rng) * (box.max[k] - box.min[k]);
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = -3;
    g.rotations[i * 4] = 1;
    for (int k = 0; k < 48; ++k) g.sh[i * 48 + k] = s(rng);
  }
  return g;
}

// Per-timestamp cost of a served scene over `repeats` distinct timestamps (after a warm-up one).
void TimeServe(size_t n, const std::string& name, field::ServedScene& sf, double setup_ms, int repeats,
               ThreadPool& pool) {
  double total = 0, cpu = 0;
  for (int r = 0; r <= repeats; ++r) {
    const auto t1 = Clock::now();
    const double c1 = CpuMs();
    absl::StatusOr<const GaussianStore*> s = sf.At(100'000 * (r + 1), pool);  // distinct timestamps
    const double ms = Ms(t1), cms = CpuMs() - c1;
    if (!s.ok()) std::exit(1);
    if (r > 0) total += ms, cpu += cms;  // the first call warms the workspace (creates a device field)
  }
  if (sf.device() == "cpu" && name.find("vulkan") != std::string::npos) {
    std::printf("      (the Vulkan field failed: these are cpu times, see the log)\n");
  }
  std::printf("serve %8zu %-13s dynamic %7zu (%5.1f %%)  setup %8.0f ms  per timestamp %7.1f ms wall, %7.1f ms cpu\n",
              n, name.c_str(), sf.num_dynamic(), 100.0 * sf.num_dynamic() / n, setup_ms, total / repeats,
              cpu / repeats);
}

// The serving form on a Vulkan engine (the server's --backend vulkan --field-device vulkan): its
// compute kernel writing a new time into the engine's scene, against the host form's evaluation
// plus the engine's upload of the whole scene (what the server did before the kernel). Wall time
// per timestamp, each call waits for the device.
void TimeFormOnVulkanEngine(size_t n, ServingForm& form, int repeats, ThreadPool& pool) {
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateVulkanEngine(VulkanDevicePreference::kGpu);
  if (!engine.ok()) {
    std::printf("      (no Vulkan engine: %s)\n", std::string(engine.status().message()).c_str());
    return;
  }
  absl::StatusOr<const GaussianStore*> first = form.At(0, pool);
  if (!first.ok()) std::exit(1);
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(**first);
  const auto t0 = Clock::now();
  absl::StatusOr<std::unique_ptr<VulkanServingForm>> kernel = VulkanServingForm::Create(**engine, form);
  const double setup_ms = Ms(t0);
  if (!scene.ok() || !kernel.ok()) {
    std::printf("      (the form's kernel failed: %s)\n",
                std::string((scene.ok() ? kernel.status() : scene.status()).message()).c_str());
    return;
  }
  double kernel_ms = 0, host_ms = 0;
  for (int r = 0; r <= repeats; ++r) {
    const int64_t t = 100'000 * (r + 1) + 50'000;
    auto t1 = Clock::now();
    if (!(*kernel)->WriteAt(t, scene->get()).ok()) std::exit(1);
    if (r > 0) kernel_ms += Ms(t1);
    t1 = Clock::now();
    absl::StatusOr<const GaussianStore*> s = form.At(t + 25'000, pool);
    if (!s.ok() || !(*engine)->UpdateSceneParams(ParamsViewOf(**s), &*scene).ok()) std::exit(1);
    if (r > 0) host_ms += Ms(t1);
  }
  std::printf("serve %8zu %-13s on %s: %zu MB of tables (%.0f ms to upload); per timestamp %7.2f ms wall "
              "(host form + whole-scene upload: %7.2f ms)\n",
              n, "form kernel", (*kernel)->device_description().c_str(), (*kernel)->device_bytes() >> 20, setup_ms,
              kernel_ms / repeats, host_ms / repeats);
}

// The serving form on the cpu engine (what `serve` does by default): a new time written straight
// into the engine's planes (HostPlanesWriter) against the host path it replaced (the form into
// the host store, then the engine's moving rows from it: UpdateSceneRows), and the LiDAR's part of
// a time (GeometryAt). Wall time per timestamp, distinct timestamps after a warm-up one.
void TimeFormOnCpuEngine(size_t n, ServingForm& form, int repeats, ThreadPool& pool) {
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  absl::StatusOr<const GaussianStore*> first = engine.ok() ? form.At(0, pool) : engine.status();
  if (!first.ok()) std::exit(1);
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(**first);
  absl::StatusOr<std::unique_ptr<DeviceSceneWriter>> writer = HostPlanesWriterFor(**engine, form, pool);
  if (!scene.ok() || !writer.ok() || !*writer) std::exit(1);
  double planes_ms = 0, host_ms = 0, geometry_ms = 0;
  for (int r = 0; r <= repeats; ++r) {
    const int64_t t = 100'000 * (r + 1) + 10'000;
    auto t1 = Clock::now();
    if (!(*writer)->WriteAt(t, scene->get()).ok()) std::exit(1);
    if (r > 0) planes_ms += Ms(t1);
    t1 = Clock::now();
    absl::StatusOr<const GaussianStore*> s = form.At(t + 20'000, pool);
    if (!s.ok() || !(*engine)->UpdateSceneRows(ParamsViewOf(**s), form.changes(), &*scene).ok()) std::exit(1);
    if (r > 0) host_ms += Ms(t1);
    t1 = Clock::now();
    if (!form.GeometryAt(t + 40'000, pool).ok()) std::exit(1);
    if (r > 0) geometry_ms += Ms(t1);
  }
  std::printf("serve %8zu %-13s into the cpu engine's planes %7.2f ms wall per timestamp (host form + row update: "
              "%7.2f ms); the LiDAR's geometry %7.2f ms\n",
              n, "form", planes_ms / repeats, host_ms / repeats, geometry_ms / repeats);
}

// The extended field on `base` with `modules`, the modules let in: the gate at 0.1 and the
// decoder's last layers Xavier x 0.1 (at init both are 0 and the extension changes nothing).
ExtendedField BenchExtension(const DeformationField& base, const std::string& modules) {
  absl::StatusOr<ExtendedFieldConfig> c = ExtendedFieldConfig::WithModules(modules);
  if (!c.ok()) {
    std::fprintf(stderr, "%s\n", std::string(c.status().message()).c_str());
    std::exit(2);
  }
  absl::StatusOr<ExtendedField> e = ExtendedField::Create(base, *c, 3);
  if (!e.ok()) std::exit(1);
  const ExtendedLayout& L = e->layout();
  std::vector<float>& p = e->mutable_params();
  if (L.has_gate) std::fill_n(p.begin() + L.gate_offset, L.model_dim, 0.1f);
  if (c->decoder) {
    std::mt19937_64 rng(4);
    for (const nn::LinearSpec* s : {&L.scale2, &L.rot2, &L.op2}) {
      nn::InitLinear<float>(*s, rng, p.data());
      for (size_t i = 0; i < size_t(s->in) * s->out; ++i) p[s->w_offset + i] *= 0.1f;
    }
  }
  return std::move(*e);
}

void BenchServe(size_t n, int repeats, int samples, double dyn_fraction, bool order,
                const std::vector<std::string>& ext_modules, bool vulkan, ThreadPool& pool) {
  FieldAabb box;
  box.min[0] = -100; box.min[1] = -100; box.min[2] = -5;
  box.max[0] = 100;  box.max[1] = 100;  box.max[2] = 15;
  const FieldTimeRange tr{0, 5'000'000};
  absl::StatusOr<DeformationField> f = DeformationField::Create(FieldConfig{}, box, tr, 1);
  if (!f.ok()) std::exit(1);
  MakeBandDynamic(&*f, dyn_fraction);
  const GaussianStore g = RandomInBox(n, box, 2);
  struct Mode {
    const char* name;
    bool skip, cache, vulkan;
  };
  std::vector<Mode> modes = {{"no-skip", false, false, false}, {"no-skip+cache", false, true, false},
                             {"skip+cache", true, true, false}};
  if (vulkan) modes.insert(modes.end(), {{"no-skip vulkan", false, false, true}, {"skip vulkan", true, false, true}});
  bool form_done = false;
  for (const Mode& mode : modes) {
    const bool skip = mode.skip;
    StaticSkipOptions o;
    o.enabled = skip;
    o.cache_spatial_features = mode.cache;
    o.num_samples = samples;
    o.spatial_order = order;
    const auto t0 = Clock::now();
    absl::StatusOr<ServingField> sf = ServingField::Create(*f, g, o, pool);
    const double setup_ms = Ms(t0);
    if (!sf.ok()) {
      std::fprintf(stderr, "%s\n", std::string(sf.status().message()).c_str());
      std::exit(1);
    }
    if (mode.vulkan) ServeOnVulkan(*sf);
    TimeServe(n, mode.name, *sf, setup_ms, repeats, pool);
    // The serving form (what `serve` evaluates by default) fitted to the field without the skip:
    // every Gaussian in its tables. Setup: the fit (the exact field sampled 2 x 4 x 24 + 4 times).
    if (std::string(mode.name) == "no-skip+cache" && !form_done) {
      form_done = true;
      const auto t1 = Clock::now();
      absl::StatusOr<std::unique_ptr<ServingForm>> form = ServingForm::Build(*sf, ServingFormOptions{}, pool);
      if (!form.ok()) std::exit(1);
      TimeServe(n, "form", **form, Ms(t1), repeats, pool);
      std::printf("      form: %zu table bytes per moving Gaussian, p99 / max position error %.2f / %.2f mm\n",
                  (*form)->table_bytes() / std::max<size_t>(1, (*form)->num_dynamic()),
                  (*form)->error().position_p99_m * 1e3, (*form)->error().max[0] * 1e3);
      TimeFormOnCpuEngine(n, **form, repeats, pool);
      if (vulkan) TimeFormOnVulkanEngine(n, **form, repeats, pool);
    }
  }
  // The extended field (ExtServingField: no spatial-feature cache, ExtendedForward per timestamp).
  for (const std::string& modules : ext_modules) {
    std::printf("extended field, modules %s:\n", modules.c_str());
    for (int row = 0; row < (vulkan ? 4 : 2); ++row) {
      const bool skip = row % 2 == 1, on_vulkan = row >= 2;
      StaticSkipOptions o;
      o.enabled = skip;
      o.num_samples = samples;
      o.spatial_order = order;
      const auto t0 = Clock::now();
      absl::StatusOr<std::unique_ptr<ExtServingField>> sf =
          ExtServingField::Create(BenchExtension(*f, modules), g, o, pool);
      const double setup_ms = Ms(t0);
      if (!sf.ok()) {
        std::fprintf(stderr, "%s\n", std::string(sf.status().message()).c_str());
        std::exit(1);
      }
      if (on_vulkan) ServeOnVulkan(**sf);
      TimeServe(n, std::string(skip ? "ext skip" : "ext no-skip") + (on_vulkan ? " vulkan" : ""), **sf, setup_ms,
                repeats, pool);
    }
  }
}

// The same Gaussians with their rows in the field's Morton order (SpatialOrder).
GaussianStore InMortonOrder(const GaussianStore& g, const FieldAabb& box, ThreadPool& pool) {
  const std::vector<uint32_t> order = SpatialOrder(box, g.means.data(), g.size(), nullptr, pool);
  GaussianStore out = g;
  for (size_t r = 0; r < order.size(); ++r) {
    const size_t i = order[r];
    std::copy_n(g.means.data() + i * 3, 3, out.means.data() + r * 3);
    std::copy_n(g.sh.data() + i * 48, 48, out.sh.data() + r * 48);
  }
  return out;
}

FieldAabb BoxOf(const GaussianStore& g) {
  FieldAabb box;
  for (int k = 0; k < 3; ++k) {
    box.min[k] = 1e30;
    box.max[k] = -1e30;
  }
  for (size_t i = 0; i < g.size(); ++i)
    for (int k = 0; k < 3; ++k) {
      box.min[k] = std::min<double>(box.min[k], g.means[i * 3 + k]);
      box.max[k] = std::max<double>(box.max[k], g.means[i * 3 + k]);
    }
  return box;
}

// One training step's field parts over the Gaussians of `g` (SH degree 3), `label` names the row.
void BenchTrain(const GaussianStore& g, const std::string& label, int repeats, ThreadPool& pool) {
  const size_t n = g.size();
  const FieldAabb box = BoxOf(g);
  absl::StatusOr<DeformationField> f = DeformationField::Create(FieldConfig{}, box, {0, 5'000'000}, 1);
  if (!f.ok()) std::exit(1);
  FieldWorkspace ws;
  DeformedScene d;
  CanonicalView cv{n, g.means.data(), g.sh.data()};
  std::vector<float> d_field;  // sized (on huge pages) by DeformBackward
  FieldAdamState adam;
  FieldHyper hyper;
  std::mt19937_64 rng(5);
  std::normal_distribution<float> nd(0, 1e-3f);
  GaussianGrads grads;
  double t_fwd = 0, t_bwd = 0, t_zero = 0, t_reg = 0, t_adam = 0, t_rows = 0, t_scatter = 0, t_cpu = 0;
  for (int r = 0; r <= repeats; ++r) {
    grads.means.resize(n * 3);
    grads.sh.resize(n * 48);
    for (float& x : grads.means) x = nd(rng);
    for (float& x : grads.sh) x = nd(rng);
    auto t0 = Clock::now();
    (void)DeformScene(*f, f->TimeCoordinate(r * 250'000), cv, pool, ws, &d);
    const double a = Ms(t0);
    const double cpu0 = CpuMs();
    t0 = Clock::now();
    pool.ParallelFor(static_cast<int64_t>(d_field.size()), 1 << 18, [&](int64_t b, int64_t e, int) {
      std::memset(d_field.data() + b, 0, (e - b) * sizeof(float));
    });
    const double z = Ms(t0);
    t0 = Clock::now();
    (void)DeformBackward(*f, cv, d, 3, hyper, pool, ws, &grads, &d_field);
    const double b = Ms(t0);
    t0 = Clock::now();
    PlaneRegularizers<float>(f->layout(), f->params().data(),
                             {hyper.plane_tv_weight, hyper.time_smoothness_weight, hyper.l1_time_planes},
                             d_field.data(), pool);
    const double c = Ms(t0);
    t0 = Clock::now();
    FieldAdamStep(f->layout(), f->mutable_params().data(), d_field.data(), &adam,
                  FieldLearningRates(hyper, r + 1, 20.0), pool);
    const double e = Ms(t0);
    const double cpu_step = CpuMs() - cpu0;
    if (r == 0) continue;  // warm-up: first-touch page faults of the workspaces and moments
    t_fwd += a;
    t_zero += z;
    t_bwd += b;
    t_reg += c;
    t_adam += e;
    t_rows += ws.last_rows_ms;
    t_cpu += cpu_step;
    t_scatter += ws.last_scatter_ms;
  }
  // The alternative to the per-plane scatter: per-thread gradient arrays of every plane, zeroed
  // and merged each step. Its fixed cost, measured here: zero one array per thread, add them.
  double t_alt = 0;
  {
    const int nt = pool.num_threads();
    std::vector<std::vector<float>> per_thread(nt, std::vector<float>(f->layout().grid_size, 0.0f));
    for (int r = 0; r <= repeats; ++r) {
      const auto t0 = Clock::now();
      const int64_t G = static_cast<int64_t>(f->layout().grid_size);
      pool.ParallelFor(G, 1 << 18, [&](int64_t b, int64_t e, int) {
        for (int t = 0; t < nt; ++t) std::memset(per_thread[t].data() + b, 0, (e - b) * sizeof(float));
      });
      pool.ParallelFor(G, 1 << 18, [&](int64_t b, int64_t e, int) {
        for (int t = 0; t < nt; ++t)
          for (int64_t i = b; i < e; ++i) d_field[i] += per_thread[t][i];
      });
      if (r > 0) t_alt += Ms(t0);
    }
  }
  const double k = 1.0 / repeats;
  std::printf("%s\n", label.c_str());
  std::printf("train %8zu  forward %7.1f  backward %7.1f  (fwd+bwd %7.1f)  zero-grad %6.1f  regularisers %6.1f  "
              "adam %6.1f  total %7.1f ms\n",
              n, t_fwd * k, t_bwd * k, (t_fwd + t_bwd) * k, t_zero * k, t_reg * k, t_adam * k,
              (t_fwd + t_bwd + t_zero + t_reg + t_adam) * k);
  std::printf("      %8s  backward phases: rows %7.1f, per-plane scatter %6.1f ms; per-thread arrays instead "
              "would add %6.1f ms (zero + merge) per step\n",
              "", t_rows * k, t_scatter * k, t_alt * k);
  std::printf("      %8s  process CPU time of a whole step (forward .. adam, all threads): %7.1f ms\n", "", t_cpu * k);
}

}  // namespace

int main(int argc, char** argv) {
  std::string serve = "500000", train = "139000,300000", ext = "all;encoder,vae,attention,gru,decoder";
  int repeats = 5, samples = 50, threads = 0;
  double dyn = 0.1;
  bool order = true, vulkan = false;
  std::string train_ply;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--serve") && i + 1 < argc) serve = argv[++i];
    else if (!std::strcmp(argv[i], "--train") && i + 1 < argc) train = argv[++i];
    else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) repeats = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--samples") && i + 1 < argc) samples = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--dynamic-fraction") && i + 1 < argc) dyn = std::atof(argv[++i]);
    else if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) threads = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--row-order")) order = false;
    else if (!std::strcmp(argv[i], "--ext-modules") && i + 1 < argc) ext = argv[++i];
    else if (!std::strcmp(argv[i], "--serve-vulkan")) vulkan = true;
    else if (!std::strcmp(argv[i], "--train-ply") && i + 1 < argc) train_ply = argv[++i];
    else {
      std::fprintf(stderr,
                   "usage: field_bench [--serve N,...] [--train N,...] [--repeats R] [--samples S] "
                   "[--dynamic-fraction F] [--threads T] [--row-order] [--ext-modules 'LIST;LIST'] [--serve-vulkan] [--train-ply SCENE.ply]\n");
      return 2;
    }
  }
  ThreadPool pool(threads);
  std::printf("field: spec sizes (35.7M plane parameters), %d threads, times averaged over %d repeats\n",
              pool.num_threads(), repeats);
  const std::vector<std::string> ext_modules = absl::StrSplit(ext, ';', absl::SkipEmpty());
  for (size_t n : ParseSizes(serve)) BenchServe(n, repeats, samples, dyn, order, ext_modules, vulkan, pool);
  for (size_t n : ParseSizes(train)) {
    BenchTrain(MakeSyntheticStreet({.num_gaussians = n, .seed = 3, .sh_degree = 3}), "procedural street", repeats,
               pool);
  }
  if (!train_ply.empty()) {
    // A trained scene's Gaussians in its own row order (the trainer's: LiDAR init, then
    // densification's clones appended) and in the field's Morton order.
    absl::StatusOr<GaussianStore> g = ReadGaussianPly(train_ply);
    if (!g.ok() || g->sh_degree != 3) {
      std::fprintf(stderr, "%s: %s\n", train_ply.c_str(),
                   g.ok() ? "needs SH degree 3" : std::string(g.status().message()).c_str());
      return 1;
    }
    BenchTrain(*g, train_ply + ": rows as stored", repeats, pool);
    BenchTrain(InMortonOrder(*g, BoxOf(*g), pool), train_ply + ": rows in Morton order", repeats, pool);
  }
  return 0;
}
