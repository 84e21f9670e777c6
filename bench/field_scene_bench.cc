// The static skip (scene/field/static_skip.h) on a trained scene rather than a synthetic field:
// how far each Gaussian's learned deformation varies over the log, how many Gaussians a pair of
// thresholds leaves static, and what a served timestamp then costs (docs/field.md "Serving").
//   field_scene_bench --scene DIR [--samples 50] [--repeats 5] [--threads 0]
//                     [--thresholds 0.01:0.01,0.02:0.02,0.05:0.05,0.1:0.1]   (motion m : ΔSH; 1e9 = no test)
// Also: the range of the scene-mean Δx over the log, and the Δx boxes with that shift or with a
// rigid motion of the whole scene fitted per time (Kabsch) removed (a field that only corrected
// the poses would move every Gaussian alike: small residual boxes).
// DIR is a trained scene directory, loaded and served as `streetsim eval --served` does
// (train::LoadSceneField, train::MakeServedScene); with field_ext.bin (--field extended) only the
// static share and the served cost per threshold pair. The ranges are AnalyseStatic's: per
// Gaussian the diagonal of its Δx box and the largest ΔSH range over the samples (times spread
// over the log, ends included). With the extended decoder: how far its Δlog-scale reaches.
#include <algorithm>
#include <cmath>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <Eigen/SVD>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "scene/field/field_eval.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/field_io.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/served_scene.h"

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
// Per sample, the sums that fit one rigid motion to every Gaussian's x -> x + Δx (Kabsch).
struct RigidSums {
  Eigen::Vector3d sx = Eigen::Vector3d::Zero(), sy = Eigen::Vector3d::Zero();
  Eigen::Matrix3d sxy = Eigen::Matrix3d::Zero();
  double n = 0;
  Eigen::Vector3d MeanShift() const { return (sy - sx) / n; }
  // The least-squares rigid motion y ~ R x + t.
  Eigen::Isometry3d Fit() const {
    const Eigen::Vector3d cx = sx / n, cy = sy / n;
    const Eigen::Matrix3d H = sxy / n - cx * cy.transpose();
    Eigen::JacobiSVD<Eigen::Matrix3d> svd(H, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
    D(2, 2) = (svd.matrixV() * svd.matrixU().transpose()).determinant() < 0 ? -1 : 1;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = svd.matrixV() * D * svd.matrixU().transpose();
    T.translation() = cy - T.linear() * cx;
    return T;
  }
};

// `motion` (optional, one per sample): the Δx it implies, T x - x, is removed from every Δx of
// that sample first. `sums` (optional): filled per sample.
std::vector<std::pair<float, float>> Ranges(const DeformationField& f, const GaussianStore& g, int samples,
                                            ThreadPool& pool, const std::vector<Eigen::Isometry3d>* motion = nullptr,
                                            std::vector<RigidSums>* sums = nullptr) {
  const size_t n = g.size(), chunk = 1 << 16;
  const int K3 = g.sh_coeffs() * 3;
  std::vector<std::pair<float, float>> out(n);
  std::vector<float> spatial, dx, dsh;
  FieldWorkspace ws;
  DeltaRanges r;
  if (sums) sums->assign(samples, RigidSums());
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
      for (size_t i = 0; i < cn; ++i) {
        const Eigen::Vector3d x(g.means[(c0 + i) * 3], g.means[(c0 + i) * 3 + 1], g.means[(c0 + i) * 3 + 2]);
        const Eigen::Vector3d y = x + Eigen::Vector3d(dx[i * 3], dx[i * 3 + 1], dx[i * 3 + 2]);
        if (sums) {
          RigidSums& r = (*sums)[s];
          r.sx += x, r.sy += y, r.sxy += x * y.transpose(), r.n += 1;
        }
        if (motion) {
          const Eigen::Vector3d rigid = (*motion)[s] * x - x;
          for (int k = 0; k < 3; ++k) dx[i * 3 + k] -= static_cast<float>(rigid[k]);
        }
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

// Wall ms per served timestamp over `repeats` distinct times inside the log (after a warm-up one).
double MsPerTimestamp(ServedScene& sf, const FieldTimeRange& tr, int repeats, ThreadPool& pool) {
  double total = 0;
  for (int r = 0; r <= repeats; ++r) {
    const int64_t t_us = tr.start_us + (tr.end_us - tr.start_us) * (r + 1) / (repeats + 2);
    const auto t1 = Clock::now();
    if (!sf.At(t_us, pool).ok()) Die(1, "serving failed");
    if (r > 0) total += Ms(t1);  // the first timestamp warms the workspace
  }
  return total / repeats;
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
  if (g->sh_degree != 3) Die(2, "a scene with a field has SH degree 3 Gaussians");
  // field.bin, and field_ext.bin checked against it, as the CLI and the server load them.
  absl::StatusOr<std::shared_ptr<const DeformationField>> field = train::LoadSceneField(dir);
  if (!field.ok()) Die(2, std::string(field.status().message()));
  if (!*field) Die(2, dir + " has no " + kFieldFileName + ": a static scene has nothing to skip");
  const DeformationField& f = **field;
  // --field extended: its Δs come out of ExtendedForward, so only the serving analysis's counts
  // are shown (ExtServingField: Δx, ΔSH and the decoder's Δs against their thresholds).
  const std::shared_ptr<const ExtendedField> ext = ExtensionOf(f);
  ThreadPool pool(threads);
  const size_t n = g->size();
  std::printf("scene %s: %zu Gaussians, %s, field over %.3f s, %d samples, %d threads\n", dir.c_str(), n,
              ext ? ("extended field (modules " + ext->config().ModulesString() + ")").c_str() : "S3Gaussian's field",
              (f.time_range().end_us - f.time_range().start_us) * 1e-6, samples, pool.num_threads());
  std::vector<float> motion, colour;  // per Gaussian (S3Gaussian's field only)
  if (!ext) {
    auto t0 = Clock::now();
    std::vector<RigidSums> sums;
    const std::vector<std::pair<float, float>> ranges = Ranges(f, *g, samples, pool, nullptr, &sums);
    std::printf("ranges over the log: %.0f ms\n", Ms(t0));
    // Is the learned motion one motion of the whole scene per time (what a pose error would ask
    // for), a shift or a rigid motion, or each Gaussian's own? Boxes with either removed.
    {
      std::vector<Eigen::Isometry3d> shift(samples, Eigen::Isometry3d::Identity()), rigid(samples);
      Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e30), hi = -lo;
      double max_angle = 0;
      for (int s = 0; s < samples; ++s) {
        shift[s].translation() = sums[s].MeanShift();
        lo = lo.cwiseMin(shift[s].translation()), hi = hi.cwiseMax(shift[s].translation());
        rigid[s] = sums[s].Fit();
        max_angle = std::max(max_angle, Eigen::AngleAxisd(rigid[s].linear()).angle());
      }
      std::printf("scene-mean Δx over the log: range %.4f %.4f %.4f m; fitted rigid motion: up to %.4f deg\n",
                  hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], max_angle * 180 / M_PI);
      for (const auto& [name, m] : {std::pair<const char*, const std::vector<Eigen::Isometry3d>*>{"scene-mean shift", &shift},
                                    {"fitted rigid motion", &rigid}}) {
        const std::vector<std::pair<float, float>> rel = Ranges(f, *g, samples, pool, m);
        std::vector<float> box(n);
        for (size_t i = 0; i < n; ++i) box[i] = rel[i].first;
        std::printf("Δx box diagonal minus the %s: p10 %.4f p50 %.4f p90 %.4f m\n", name, Quantile(box, 0.1),
                    Quantile(box, 0.5), Quantile(box, 0.9));
      }
    }
    motion.resize(n);
    colour.resize(n);
    for (size_t i = 0; i < n; ++i) motion[i] = ranges[i].first, colour[i] = ranges[i].second;
    std::printf("%-28s %9s %9s %9s %9s %9s\n", "per Gaussian, over the log", "p10", "p50", "p90", "p99", "max");
    std::printf("%-28s", "Δx box diagonal (m)");
    for (double q : {0.1, 0.5, 0.9, 0.99, 1.0}) std::printf(" %9.4f", Quantile(motion, q));
    std::printf("\n%-28s", "max ΔSH range");
    for (double q : {0.1, 0.5, 0.9, 0.99, 1.0}) std::printf(" %9.4f", Quantile(colour, q));
    std::printf("\n");
  }
  if (ext && ext->config().decoder) {
    // The decoder's Δlog-scale as the scene applies it (unbounded before field_ext.bin version 3,
    // docs/field.md "The decoder's Δlog-scale"): how far it reaches on a trained scene, per Gaussian
    // the largest |Δ| over axes and times, and the largest deformed log-scale (exp of it = the
    // longest axis in metres).
    auto t0 = Clock::now();
    std::vector<float> reach(n, 0.0f), longest(n, -1e30f);
    for (int smp = 0; smp < samples; ++smp) {
      const int64_t t_us =
          f.time_range().start_us + (f.time_range().end_us - f.time_range().start_us) * smp / (samples - 1);
      absl::StatusOr<GaussianStore> d = train::DeformedStore(f, *g, t_us, pool);
      if (!d.ok()) Die(1, std::string(d.status().message()));
      for (size_t i = 0; i < n * 3; ++i) {
        reach[i / 3] = std::max(reach[i / 3], std::abs(d->log_scales[i] - g->log_scales[i]));
        longest[i / 3] = std::max(longest[i / 3], d->log_scales[i]);
      }
    }
    // A bounded decoder saturates at B (the ulp above ln 10 that B tanh(.) may round to is not "over").
    const float bound = ext->config().decoder_max_dlog_scale;
    size_t over_ln10 = 0, over_5 = 0, over_1km = 0, at_bound = 0;
    for (size_t i = 0; i < n; ++i) {
      over_ln10 += reach[i] > std::log(10.0f) * 1.00001f, over_5 += reach[i] > 5.0f;
      over_1km += longest[i] > std::log(1000.0f), at_bound += bound > 0 && reach[i] >= 0.99f * bound;
    }
    std::printf("decoder over the log (%.0f ms):\n%-28s %9s %9s %9s %9s %9s\n", Ms(t0), "per Gaussian", "p50", "p90",
                "p99", "p99.9", "max");
    std::printf("%-28s", "max |Δlog-scale|");
    for (double q : {0.5, 0.9, 0.99, 0.999, 1.0}) std::printf(" %9.3f", Quantile(reach, q));
    std::printf("\n%-28s", "max deformed log-scale");
    for (double q : {0.5, 0.9, 0.99, 0.999, 1.0}) std::printf(" %9.3f", Quantile(longest, q));
    std::printf("\n|Δlog-scale| > ln 10: %zu Gaussians, > 5: %zu; an axis over 1 km at some time: %zu\n", over_ln10,
                over_5, over_1km);
    if (bound > 0) std::printf("bound B = %.4f: %zu Gaussians reach 0.99 B at some time\n", bound, at_bound);
    else std::printf("unbounded decoder (B = 0: field_ext.bin before version 3)\n");
  }
  std::printf("\n%10s %8s | %9s %9s %9s | %10s %14s\n", "motion m", "ΔSH", "motion ok", "ΔSH ok", "static",
              "setup ms", "ms / timestamp");
  for (const auto& [m, s] : pairs) {
    size_t mo = 0, so = 0, both = 0;
    for (size_t i = 0; i < motion.size(); ++i) {
      const bool a = motion[i] < m, b = colour[i] < s;
      mo += a, so += b, both += a && b;
    }
    StaticSkipOptions o;
    o.num_samples = samples;
    o.motion_threshold_m = m;
    o.sh_threshold = s;
    const auto t0 = Clock::now();
    absl::StatusOr<std::shared_ptr<ServedScene>> sf = train::MakeServedScene(*field, *g, o, &pool);
    const double setup_ms = Ms(t0);
    if (!sf.ok()) Die(1, std::string(sf.status().message()));
    const size_t num_static = (*sf)->size() - (*sf)->num_dynamic();
    if (!ext && num_static != both) {
      Die(1, "the serving analysis disagrees with this bench's ranges (static " + std::to_string(num_static) +
                 " vs " + std::to_string(both) + ")");
    }
    const double ms = MsPerTimestamp(**sf, f.time_range(), repeats, pool);
    if (ext) {
      std::printf("%10g %8g | %9s %9s %8.1f%% | %10.0f %14.1f\n", m, s, "-", "-", 100.0 * num_static / n, setup_ms, ms);
    } else {
      std::printf("%10g %8g | %8.1f%% %8.1f%% %8.1f%% | %10.0f %14.1f\n", m, s, 100.0 * mo / n, 100.0 * so / n,
                  100.0 * num_static / n, setup_ms, ms);
    }
  }
  return 0;
}
