// The static skip (scene/field/static_skip.h) on a trained scene rather than a synthetic field:
// how far each Gaussian's learned deformation varies over the log, how many Gaussians a pair of
// thresholds leaves static, and what a served timestamp then costs (docs/field.md "Serving").
//   field_scene_bench --scene DIR [--samples 50] [--repeats 5] [--threads 0]
//                     [--thresholds 0.01:0.01,0.02:0.02,0.05:0.05,0.1:0.1]   (motion m : ΔSH; 1e9 = no test)
// Also: the range of the scene-mean Δx over the log and the Δx box with that shift removed (a
// field that only corrected the poses would move every Gaussian alike: small residual boxes).
// DIR is a trained scene directory (scene.ply + field.bin, S3Gaussian's field). The ranges are
// AnalyseStatic's: per Gaussian the diagonal of its Δx box and the largest ΔSH range over the
// samples (times spread over the log, ends included).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "scene/field/field_eval.h"
#include "scene/field/field_io.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/ply_io.h"

using namespace streetsim;
using namespace streetsim::field;
using Clock = std::chrono::steady_clock;

namespace {

double Ms(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

[[noreturn]] void Die(int code, const std::string& why) {
  std::fprintf(stderr, "field_scene_bench: %s\n", why.c_str());
  std::exit(code);
}

// Per Gaussian: {diagonal of the Δx range box (m), largest ΔSH range over the store's coefficients}.
// `shift` (optional, [samples * 3]): subtracted from every Δx of sample s first.
std::vector<std::pair<float, float>> Ranges(const DeformationField& f, const GaussianStore& g, int samples,
                                            ThreadPool& pool, const std::vector<double>* shift = nullptr,
                                            std::vector<double>* mean_dx = nullptr) {
  const size_t n = g.size(), chunk = 1 << 16;
  const int K3 = g.sh_coeffs() * 3;
  std::vector<std::pair<float, float>> out(n);
  std::vector<float> spatial, dx, dsh;
  FieldWorkspace ws;
  DeltaRanges r;
  if (mean_dx) mean_dx->assign(samples * 3, 0.0);
  for (size_t c0 = 0; c0 < n; c0 += chunk) {
    const size_t cn = std::min(chunk, n - c0);
    spatial.resize(cn * f.layout().feature_dim());
    dx.resize(cn * 3);
    dsh.resize(cn * kShOutputs);
    SpatialFeatures<float>(f.layout(), f.params().data(), f.QueryAtCoordinate(0), g.means.data() + c0 * 3, nullptr,
                           cn, spatial.data(), pool);
    r.Reset(cn, 3 + K3);
    for (int s = 0; s < samples; ++s) {
      const double coord = f.NormalisedTime(static_cast<double>(s) / (samples - 1));
      FieldForwardCached<float>(f.layout(), f.params().data(), f.QueryAtCoordinate(coord), g.means.data() + c0 * 3,
                                nullptr, spatial.data(), cn, dx.data(), dsh.data(), pool, ws);
      for (size_t i = 0; i < cn; ++i)
        for (int k = 0; k < 3; ++k) {
          if (mean_dx) (*mean_dx)[s * 3 + k] += dx[i * 3 + k] / double(g.size());
          if (shift) dx[i * 3 + k] -= static_cast<float>((*shift)[s * 3 + k]);
        }
      r.Add({{dx.data(), 3, 3}, {dsh.data(), kShOutputs, K3}}, pool);
    }
    for (size_t i = 0; i < cn; ++i) {
      double box2 = 0;
      for (int k = 0; k < 3; ++k) box2 += double(r.range(i, k)) * r.range(i, k);
      out[c0 + i] = {static_cast<float>(std::sqrt(box2)), static_cast<float>(r.max_range(i, 3, K3))};
    }
  }
  return out;
}

float Quantile(std::vector<float> v, double q) {
  const size_t k = std::min(v.size() - 1, static_cast<size_t>(q * (v.size() - 1)));
  std::nth_element(v.begin(), v.begin() + k, v.end());
  return v[k];
}

}  // namespace

int main(int argc, char** argv) {
  std::string dir, thresholds = "0.01:0.01,0.02:0.02,0.05:0.05,0.1:0.1";
  int samples = 50, repeats = 5, threads = 0;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--scene") && i + 1 < argc) dir = argv[++i];
    else if (!std::strcmp(argv[i], "--samples") && i + 1 < argc) samples = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) repeats = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) threads = std::atoi(argv[++i]);
    else if (!std::strcmp(argv[i], "--thresholds") && i + 1 < argc) thresholds = argv[++i];
    else Die(2, "usage: field_scene_bench --scene DIR [--samples S] [--repeats R] [--threads T] [--thresholds M:S,...]");
  }
  if (dir.empty()) Die(2, "--scene DIR is required");
  if (samples < 2 || samples > 10000) Die(2, "--samples must be in 2..10000");
  std::vector<std::pair<double, double>> pairs;
  for (const std::string& p : std::vector<std::string>(absl::StrSplit(thresholds, ',', absl::SkipEmpty()))) {
    std::vector<std::string> ms = absl::StrSplit(p, ':');
    double m = 0, s = 0;
    if (ms.size() != 2 || !absl::SimpleAtod(ms[0], &m) || !absl::SimpleAtod(ms[1], &s) || !(m >= 0) || !(s >= 0)) {
      Die(2, "--thresholds wants MOTION_M:SH pairs, e.g. 0.01:0.01,0.05:0.05");
    }
    pairs.emplace_back(m, s);
  }
  absl::StatusOr<GaussianStore> g = ReadGaussianPly((std::filesystem::path(dir) / "scene.ply").string());
  if (!g.ok()) Die(2, std::string(g.status().message()));
  absl::StatusOr<DeformationField> f = LoadField((std::filesystem::path(dir) / kFieldFileName).string());
  if (!f.ok()) Die(2, std::string(f.status().message()));
  if (g->sh_degree != 3) Die(2, "a scene with a field has SH degree 3 Gaussians");
  ThreadPool pool(threads);
  const size_t n = g->size();
  std::printf("scene %s: %zu Gaussians, field over %.3f s, %d samples, %d threads\n", dir.c_str(), n,
              (f->time_range().end_us - f->time_range().start_us) * 1e-6, samples, pool.num_threads());

  auto t0 = Clock::now();
  std::vector<double> mean_dx;
  const std::vector<std::pair<float, float>> ranges = Ranges(*f, *g, samples, pool, nullptr, &mean_dx);
  std::printf("ranges over the log: %.0f ms\n", Ms(t0));
  {
    double lo[3] = {1e30, 1e30, 1e30}, hi[3] = {-1e30, -1e30, -1e30};
    for (int s = 0; s < samples; ++s)
      for (int k = 0; k < 3; ++k) lo[k] = std::min(lo[k], mean_dx[s * 3 + k]), hi[k] = std::max(hi[k], mean_dx[s * 3 + k]);
    std::printf("scene-mean Δx over the log: range %.4f %.4f %.4f m\n", hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
    const std::vector<std::pair<float, float>> rel = Ranges(*f, *g, samples, pool, &mean_dx);
    std::vector<float> m(n);
    for (size_t i = 0; i < n; ++i) m[i] = rel[i].first;
    std::printf("Δx box diagonal minus the scene-mean shift: p10 %.4f p50 %.4f p90 %.4f m\n", Quantile(m, 0.1),
                Quantile(m, 0.5), Quantile(m, 0.9));
  }
  std::vector<float> motion(n), colour(n);
  for (size_t i = 0; i < n; ++i) motion[i] = ranges[i].first, colour[i] = ranges[i].second;
  std::printf("%-28s %9s %9s %9s %9s %9s\n", "per Gaussian, over the log", "p10", "p50", "p90", "p99", "max");
  std::printf("%-28s", "Δx box diagonal (m)");
  for (double q : {0.1, 0.5, 0.9, 0.99, 1.0}) std::printf(" %9.4f", Quantile(motion, q));
  std::printf("\n%-28s", "max ΔSH range");
  for (double q : {0.1, 0.5, 0.9, 0.99, 1.0}) std::printf(" %9.4f", Quantile(colour, q));
  std::printf("\n\n%10s %8s | %9s %9s %9s | %10s %14s\n", "motion m", "ΔSH", "motion ok", "ΔSH ok", "static",
              "setup ms", "ms / timestamp");
  for (const auto& [m, s] : pairs) {
    size_t mo = 0, so = 0, both = 0;
    for (size_t i = 0; i < n; ++i) {
      const bool a = motion[i] < m, b = colour[i] < s;
      mo += a, so += b, both += a && b;
    }
    StaticSkipOptions o;
    o.num_samples = samples;
    o.motion_threshold_m = m;
    o.sh_threshold = s;
    t0 = Clock::now();
    absl::StatusOr<ServingField> sf = ServingField::Create(*f, *g, o, pool);
    const double setup_ms = Ms(t0);
    if (!sf.ok()) Die(1, std::string(sf.status().message()));
    if (sf->size() - sf->num_dynamic() != both) {
      Die(1, "the serving analysis disagrees with this bench's ranges (static " +
                 std::to_string(sf->size() - sf->num_dynamic()) + " vs " + std::to_string(both) + ")");
    }
    double total = 0;
    for (int r = 0; r <= repeats; ++r) {
      const int64_t t_us = f->time_range().start_us +
                           (f->time_range().end_us - f->time_range().start_us) * (r + 1) / (repeats + 2);
      const auto t1 = Clock::now();
      if (!sf->At(t_us, pool).ok()) Die(1, "serving failed");
      if (r > 0) total += Ms(t1);  // the first timestamp warms the workspace
    }
    std::printf("%10g %8g | %8.1f%% %8.1f%% %8.1f%% | %10.0f %14.1f\n", m, s, 100.0 * mo / n, 100.0 * so / n,
                100.0 * both / n, setup_ms, total / repeats);
  }
  return 0;
}
