#include "render/lidar/lidar_backward.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "render/common/projection_backward_math.h"
#include "render/cpu/simd_dispatch.h"

namespace streetsim {
namespace lidar {
namespace {

constexpr int kG = kLidarSplatGradSize;

// One tile: replay the forward (final T, last contributor per pixel), then walk the list back to
// front; acc [N * kG] is this thread's per-Gaussian sum, or, with per_instance, each (splat, tile)
// pair's terms go to per_instance[list position * kG] (the deterministic mode).
template <typename Real>
void BlendBackwardTile(const LidarBackwardView<Real>& f, const LidarUpstreamGradsT<Real>& up, int64_t tile,
                       Real* acc, Real* per_instance) {
  const int tx = static_cast<int>(tile % f.tiles_x), ty = static_cast<int>(tile / f.tiles_x);
  const int x0 = tx * kTile, y0 = ty * kTile;
  const int rows = std::min(kTile, f.beams - y0), cols = std::min(kTile, f.columns - x0);
  const uint32_t begin = f.tile_offsets[tile], end = f.tile_offsets[tile + 1];
  if (begin == end) return;
  Real T[kTile * kTile], D[kTile * kTile], I[kTile * kTile];
  int32_t last[kTile * kTile];
  BlendTileRef(f.splats, f.tile_ids, begin, end, x0, y0, rows, cols, T, D, I, last);

  // Per pixel: upstream gradients, T walking back from the final value, and the normalised
  // suffix sums of range and reflectance behind the current splat (the camera's S).
  Real gD[kTile * kTile], gI[kTile * kTile], gAT[kTile * kTile], SD[kTile * kTile], SI[kTile * kTile];
  int32_t max_last = -1;
  for (int r = 0; r < kTile; ++r) {
    for (int c = 0; c < kTile; ++c) {
      const int p = r * kTile + c;
      gD[p] = gI[p] = gAT[p] = SD[p] = SI[p] = 0;
      if (r >= rows || c >= cols || last[p] < 0) continue;
      const size_t pix = static_cast<size_t>(y0 + r) * f.columns + x0 + c;
      gD[p] = up.d_range_sum ? up.d_range_sum[pix] : Real(0);
      gI[p] = up.d_intensity_sum ? up.d_intensity_sum[pix] : Real(0);
      // alpha_out = 1 - T_final: d alpha_out / d alpha_i = T_final / (1 - alpha_i).
      gAT[p] = (up.d_alpha ? up.d_alpha[pix] : Real(0)) * T[p];
      max_last = std::max(max_last, last[p]);
    }
  }
  for (int32_t jj = max_last; jj >= 0; --jj) {
    // Scattered splats and accumulator slots: prefetch the splat and its Gaussian index far ahead,
    // the slots (which need the index) nearer.
    if (jj >= static_cast<int32_t>(kPrefetchAhead)) {
      const uint32_t ahead = f.tile_ids[begin + jj - kPrefetchAhead];
      __builtin_prefetch(&f.splats[ahead]);
      __builtin_prefetch(&f.splat_gauss[ahead]);
    }
    if (!per_instance && jj >= static_cast<int32_t>(kPrefetchAhead / 2)) {
      __builtin_prefetch(acc + static_cast<size_t>(f.splat_gauss[f.tile_ids[begin + jj - kPrefetchAhead / 2]]) * kG, 1);
    }
    const uint32_t id = f.tile_ids[begin + jj];
    const LidarSplatT<Real>& s = f.splats[id];
    int r0, r1, c0, c1;
    OpacityBox(s, x0, y0, rows, cols, &r0, &r1, &c0, &c1);
    Real g[kG] = {0, 0, 0, 0, 0, 0, 0, 0};
    bool any = false;
    for (int r = r0; r <= r1; ++r) {
      const Real dy = s.y - static_cast<Real>(y0 + r);
      for (int c = c0; c <= c1; ++c) {
        const int p = r * kTile + c;
        if (jj > last[p]) continue;  // after the pixel's last contributor (or it stopped before)
        const Real dx = s.x - static_cast<Real>(x0 + c);
        Real G;
        const Real alpha = SplatAlpha(s, dx, dy, &G);
        if (alpha == Real(0)) continue;
        any = true;
        const Real om = Real(1) - alpha;
        const Real Ti = T[p] / om;
        const Real w = alpha * Ti;
        g[kGrange] += w * gD[p];
        g[kGrefl] += w * gI[p];
        const Real d_alpha = gAT[p] / om + Ti * (gD[p] * (s.range - SD[p]) + gI[p] * (s.refl - SI[p]));
        SD[p] = alpha * s.range + om * SD[p];
        SI[p] = alpha * s.refl + om * SI[p];
        T[p] = Ti;
        if (!(s.opacity * G < Real(kMaxAlpha))) continue;  // clamped: alpha depends on neither o nor G
        g[kGo] += d_alpha * G;
        const Real d_power = d_alpha * s.opacity * G;
        g[kGu] += d_power * -(s.a * dx + s.b * dy);
        g[kGv] += d_power * -(s.c * dy + s.b * dx);
        g[kGa] += d_power * Real(-0.5) * dx * dx;
        g[kGb] += d_power * -dx * dy;
        g[kGc] += d_power * Real(-0.5) * dy * dy;
      }
    }
    if (!any) continue;
    Real* a = per_instance ? per_instance + static_cast<size_t>(begin + jj) * kG
                           : acc + static_cast<size_t>(f.splat_gauss[id]) * kG;
    for (int k = 0; k < kG; ++k) a[k] += g[k];
  }
}

// Runs tile_fn(tile_begin, tile_end, acc, per_instance) over all tiles and sums into out [N x kG].
// Fast mode: per-thread [N x kG] arrays summed in a fixed thread order per element (which thread
// took which tile changes the rounding). Deterministic: one slot per tile-list entry, reduced in
// list order (the result is independent of the scheduling and the thread count).
template <typename Real, typename TileFn>
void AccumulateOverTiles(ThreadPool& pool, size_t num_gaussians, int64_t tiles, const uint32_t* tile_ids,
                         size_t num_instances, const uint32_t* splat_gauss, bool deterministic,
                         LidarBackwardScratch<Real>* scratch, std::vector<Real>* out, const TileFn& tile_fn) {
  const size_t n = num_gaussians * kG;
  out->resize(n);
  if (deterministic) {
    std::vector<Real>& inst = scratch->per_instance;
    inst.resize(num_instances * kG);
    pool.ParallelFor(static_cast<int64_t>(inst.size()), 1 << 16, [&](int64_t b, int64_t e, int) {
      std::memset(inst.data() + b, 0, sizeof(Real) * (e - b));
    });
    pool.ParallelFor(tiles, 1, [&](int64_t t0, int64_t t1, int) { tile_fn(t0, t1, nullptr, inst.data()); });
    std::fill(out->begin(), out->end(), Real(0));
    for (size_t j = 0; j < num_instances; ++j) {
      Real* dst = out->data() + static_cast<size_t>(splat_gauss[tile_ids[j]]) * kG;
      for (int k = 0; k < kG; ++k) dst[k] += inst[j * kG + k];
    }
    return;
  }
  std::vector<std::vector<Real>>& per_thread = scratch->per_thread;
  per_thread.resize(pool.num_threads());
  pool.ParallelFor(pool.num_threads(), 1, [&](int64_t b, int64_t e, int) {
    for (int64_t t = b; t < e; ++t) per_thread[t].assign(n, Real(0));
  });
  pool.ParallelFor(tiles, 1, [&](int64_t t0, int64_t t1, int thread) {
    tile_fn(t0, t1, per_thread[thread].data(), nullptr);
  });
  pool.ParallelFor(static_cast<int64_t>(n), 1 << 14, [&](int64_t b, int64_t e, int) {
    Real* o = out->data();
    std::memcpy(o + b, per_thread[0].data() + b, sizeof(Real) * (e - b));
    for (size_t t = 1; t < per_thread.size(); ++t) {
      const Real* src = per_thread[t].data();
      for (int64_t i = b; i < e; ++i) o[i] += src[i];
    }
  });
}

}  // namespace

template <typename Real>
void BlendBackward(ThreadPool& pool, const LidarBackwardView<Real>& view, const LidarUpstreamGradsT<Real>& up,
                   bool deterministic, LidarBackwardScratch<Real>* scratch, std::vector<Real>* out) {
  const int64_t tiles = static_cast<int64_t>(view.tiles_x) * view.tiles_y;
  AccumulateOverTiles<Real>(pool, view.num_gaussians, tiles, view.tile_ids, view.tile_offsets[tiles],
                            view.splat_gauss, deterministic, scratch, out,
                            [&](int64_t t0, int64_t t1, Real* acc, Real* per_instance) {
                              for (int64_t t = t0; t < t1; ++t) BlendBackwardTile(view, up, t, acc, per_instance);
                            });
}

void BlendBackwardVectorised(ThreadPool& pool, const LidarBackwardView<float>& view, const LidarUpstreamGrads& up,
                             bool force_avx2, bool deterministic, LidarBackwardScratch<float>* scratch,
                             std::vector<float>* out) {
  using Fn = void (*)(const LidarBlendBackwardArgs&, int64_t, int64_t, float*, float*);
  const Fn fn = force_avx2 ? simd_avx2::BlendBackwardTiles
                           : cpu::PickSimd<Fn>(simd_avx2::BlendBackwardTiles, simd_avx512::BlendBackwardTiles);
  const LidarBlendBackwardArgs args{view.splats, view.splat_gauss, view.tile_offsets, view.tile_ids,
                                    view.beams,  view.columns,     view.tiles_x,      up.d_range_sum,
                                    up.d_alpha,  up.d_intensity_sum};
  const int64_t tiles = static_cast<int64_t>(view.tiles_x) * view.tiles_y;
  AccumulateOverTiles<float>(pool, view.num_gaussians, tiles, view.tile_ids, view.tile_offsets[tiles],
                             view.splat_gauss, deterministic, scratch, out,
                             [&](int64_t t0, int64_t t1, float* acc, float* per_instance) {
                               fn(args, t0, t1, acc, per_instance);
                             });
}

template <typename Real>
void ProjectGaussianBackwardRef(const RefProjectParams<Real>& p, int col, const GaussianParams<Real>& gp,
                                const Real* g, Real* d_mean, Real* d_log_scale, Real* d_quat, Real* d_logit) {
  using std::exp;
  using std::sqrt;
  // ---- The forward, recomputed (ProjectGaussianRef) ----
  const Real* e = p.pose_table + static_cast<size_t>(col) * kPoseStride;
  const Real* W = e;
  const Real* m = gp.mean;
  const Real px = W[0] * m[0] + W[1] * m[1] + W[2] * m[2] + e[9];
  const Real py = W[3] * m[0] + W[4] * m[1] + W[5] * m[2] + e[10];
  const Real pz = W[6] * m[0] + W[7] * m[1] + W[8] * m[2] + e[11];
  const Real rho2 = px * px + py * py;
  const Real r2 = rho2 + pz * pz;
  const Real range = sqrt(r2);
  const Real rho = sqrt(rho2);
  const Real opacity = Real(1) / (Real(1) + exp(-gp.logit));

  const Real* q = gp.quat;
  const Real qinv = Real(1) / sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  const Real qw = q[0] * qinv, qx = q[1] * qinv, qy = q[2] * qinv, qz = q[3] * qinv;
  Real R[9];
  projection::QuatToRotation(q, R);
  const Real s[3] = {exp(std::clamp(gp.log_scale[0], Real(-30), Real(30))),
                     exp(std::clamp(gp.log_scale[1], Real(-30), Real(30))),
                     exp(std::clamp(gp.log_scale[2], Real(-30), Real(30)))};
  Real M[9];
  projection::ScaledRotation(R, s, M);

  double dbeam_d = 0;
  p.model->BeamCoordinate(static_cast<double>(std::atan2(pz, rho)), &dbeam_d);  // the segment: fixed
  const Real kb = static_cast<Real>(dbeam_d);
  const Real cpr = p.cols_per_rad;
  const Real ku = cpr / rho2, kv = kb / r2;
  const Real J0[3] = {ku * py, -ku * px, Real(0)};
  const Real J1[3] = {-kv * px * pz / rho, -kv * py * pz / rho, kv * rho};
  Real T0[3], T1[3];
  for (int k = 0; k < 3; ++k) {
    T0[k] = J0[0] * W[k] + J0[1] * W[3 + k] + J0[2] * W[6 + k];
    T1[k] = J1[0] * W[k] + J1[1] * W[3 + k] + J1[2] * W[6 + k];
  }
  const projection::Covariance2D<Real> cov = projection::ProjectCovariance(T0, T1, M, Real(kLowPassPx));
  const Real cxx = cov.cxx, cxy = cov.cxy, cyy = cov.cyy;
  const Real inv_det = Real(1) / cov.det;

  // ---- conic -> 2D covariance -> P = T M -> T, M = R diag(s) -> quaternion, scales ----
  Real dT0[3], dT1[3], ds_times_s[3];
  const projection::CovarianceChain<Real> chain{T0, T1, cov.p0, cov.p1, M, s, cxx, cxy, cyy, inv_det, Real(kLowPassPx), qw, qx, qy, qz, qinv};
  projection::CovarianceChainBackward(chain, g[kGa], g[kGb], g[kGc], dT0, dT1, d_quat, ds_times_s);
  for (int c = 0; c < 3; ++c) {
    const bool free = gp.log_scale[c] > Real(-30) && gp.log_scale[c] < Real(30);  // the forward's clamp
    d_log_scale[c] = free ? ds_times_s[c] : Real(0);
  }

  // ---- T = J W -> J; J, u, v, range -> sensor-frame mean p ----
  Real dJ0[3], dJ1[3];
  for (int i = 0; i < 3; ++i) {
    dJ0[i] = dT0[0] * W[i * 3] + dT0[1] * W[i * 3 + 1] + dT0[2] * W[i * 3 + 2];
    dJ1[i] = dT1[0] * W[i * 3] + dT1[1] * W[i * 3 + 1] + dT1[2] * W[i * 3 + 2];
  }
  // u and v themselves: du/dp = J0, dv/dp = J1 (their own Jacobian); range: p / |p|.
  Real dpx = g[kGu] * J0[0] + g[kGv] * J1[0] + g[kGrange] * px / range;
  Real dpy = g[kGu] * J0[1] + g[kGv] * J1[1] + g[kGrange] * py / range;
  Real dpz = g[kGv] * J1[2] + g[kGrange] * pz / range;
  // J00 = cpr py / rho2, J01 = -cpr px / rho2.
  const Real inv_rho2 = Real(1) / rho2;
  dpx += dJ0[0] * (-2 * cpr * py * px * inv_rho2 * inv_rho2);
  dpy += dJ0[0] * (cpr * inv_rho2 - 2 * cpr * py * py * inv_rho2 * inv_rho2);
  dpx += dJ0[1] * (-cpr * inv_rho2 + 2 * cpr * px * px * inv_rho2 * inv_rho2);
  dpy += dJ0[1] * (2 * cpr * px * py * inv_rho2 * inv_rho2);
  // J10 = -kb px pz f, J11 = -kb py pz f with f = 1 / (rho r2); d ln f = -(p_xy / rho2 + 2 p / r2).
  const Real f = Real(1) / (rho * r2);
  const Real lfx = -(px * inv_rho2 + 2 * px / r2), lfy = -(py * inv_rho2 + 2 * py / r2), lfz = -2 * pz / r2;
  dpx += dJ1[0] * (-kb * pz * f * (1 + px * lfx));
  dpy += dJ1[0] * (-kb * px * pz * f * lfy);
  dpz += dJ1[0] * (-kb * px * f * (1 + pz * lfz));
  dpx += dJ1[1] * (-kb * py * pz * f * lfx);
  dpy += dJ1[1] * (-kb * pz * f * (1 + py * lfy));
  dpz += dJ1[1] * (-kb * py * f * (1 + pz * lfz));
  // J12 = kb rho / r2; d ln(rho / r2) = p_xy / rho2 - 2 p / r2.
  const Real J12 = J1[2];
  dpx += dJ1[2] * J12 * (px * inv_rho2 - 2 * px / r2);
  dpy += dJ1[2] * J12 * (py * inv_rho2 - 2 * py / r2);
  dpz += dJ1[2] * J12 * (-2 * pz / r2);
  // p = W m + t.
  for (int k = 0; k < 3; ++k) d_mean[k] = W[k] * dpx + W[3 + k] * dpy + W[6 + k] * dpz;
  *d_logit = g[kGo] * opacity * (Real(1) - opacity);
}

template <typename Real>
void ProjectBackward(ThreadPool& pool, const RefProjectParams<Real>& p, const LidarSoa& soa, const float* refl,
                     const uint32_t* gauss_col, const std::vector<Real>& splat_grads,
                     LidarGaussianGradsT<Real>* out) {
  const size_t n = soa.n;
  out->means.assign(n * 3, Real(0));
  out->log_scales.assign(n * 3, Real(0));
  out->rotations.assign(n * 4, Real(0));
  out->opacity_logits.assign(n, Real(0));
  out->reflectance.assign(n, Real(0));
  pool.ParallelFor(static_cast<int64_t>(n), 2048, [&](int64_t b, int64_t e, int) {
    GaussianParams<Real> gp;
    for (int64_t i = b; i < e; ++i) {
      const Real* g = &splat_grads[static_cast<size_t>(i) * kG];
      bool any = false;
      for (int k = 0; k < kG; ++k) any |= g[k] != Real(0);
      if (!any) continue;  // not drawn (or no gradient reached it)
      GetGaussian(soa, refl, i, &gp);
      const int col = gauss_col ? static_cast<int>(gauss_col[i]) : PoseColumn(p, gp.mean);
      ProjectGaussianBackwardRef(p, col, gp, g, &out->means[i * 3], &out->log_scales[i * 3], &out->rotations[i * 4],
                                 &out->opacity_logits[i]);
      // The forward clamps reflectance to [0, 1]: no gradient through the clamp.
      const bool refl_free = !refl || (refl[i] >= 0.0f && refl[i] <= 1.0f);
      out->reflectance[i] = refl_free ? g[kGrefl] : Real(0);
    }
  });
}

template void BlendBackward<float>(ThreadPool&, const LidarBackwardView<float>&, const LidarUpstreamGradsT<float>&,
                                   bool, LidarBackwardScratch<float>*, std::vector<float>*);
template void BlendBackward<double>(ThreadPool&, const LidarBackwardView<double>&,
                                    const LidarUpstreamGradsT<double>&, bool, LidarBackwardScratch<double>*,
                                    std::vector<double>*);
template void ProjectBackward<float>(ThreadPool&, const RefProjectParams<float>&, const LidarSoa&, const float*,
                                     const uint32_t*, const std::vector<float>&, LidarGaussianGradsT<float>*);
template void ProjectBackward<double>(ThreadPool&, const RefProjectParams<double>&, const LidarSoa&, const float*,
                                      const uint32_t*, const std::vector<double>&, LidarGaussianGradsT<double>*);

}  // namespace lidar

absl::Status RenderLidarReference(ThreadPool& pool, const GaussianStore& store, const LidarModel& model,
                                  const LidarSweepPose& sweep, const std::vector<float>* reflectance,
                                  LidarReferenceOutput* out, const LidarUpstreamGradsT<double>* upstream,
                                  LidarGaussianGradsT<double>* grads) {
  using namespace lidar;
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  if (absl::Status s = model.Validate(); !s.ok()) return s;
  if (absl::Status s = ValidateSweepPose(sweep); !s.ok()) return s;
  const size_t n = store.size();
  if (reflectance && reflectance->size() != n) {
    return absl::InvalidArgumentError(absl::StrCat("reflectance has ", reflectance->size(), " values for ", n,
                                                   " Gaussians"));
  }
  LidarSoa soa;
  CopyToSoa(pool, store, &soa);
  const float* refl = reflectance ? reflectance->data() : nullptr;
  const int B = model.beams(), W = model.columns;
  std::vector<double> table;
  ColumnPoseTable(sweep, W, &table);
  RefProjectParams<double> p;
  p.model = &model;
  p.pose_table = table.data();
  p.rolling = !sweep.is_static();
  p.near_m = std::max(static_cast<double>(kNearM), model.min_range_m);
  p.far_m = model.max_range_m;
  p.cols_per_rad = W / (2 * M_PI);
  p.columns = W;
  p.beams = B;
  p.tiles_x = (W + kTile - 1) / kTile;
  p.tiles_y = (B + kTile - 1) / kTile;

  std::vector<LidarSplatT<double>> splats(2 * n);
  std::vector<Rect> rects(2 * n);
  std::vector<uint32_t> keys(2 * n), gauss(2 * n);
  LidarProjectOutT<double> po{splats.data(), rects.data(), keys.data(), gauss.data(), 0};
  GaussianParams<double> gp;
  for (size_t i = 0; i < n; ++i) {
    GetGaussian(soa, refl, i, &gp);
    LidarSplatT<double> sp;
    double half_w, half_h;
    if (!ProjectGaussianRef(p, PoseColumn(p, gp.mean), gp, &sp, &half_w, &half_h)) continue;
    FillSplat(W, B, p.tiles_x, p.tiles_y, sp, half_w, half_h, static_cast<uint32_t>(i), &po);
  }
  keys.resize(po.count);
  std::vector<uint32_t> ids(po.count), tile_offsets, tile_ids;
  for (uint32_t k = 0; k < po.count; ++k) ids[k] = k;
  BinScratch scratch;
  SortAndBin(pool, &keys, &ids, rects.data(), p.tiles_x, p.tiles_y, &scratch, &tile_offsets, &tile_ids);

  const size_t P = static_cast<size_t>(B) * W;
  out->range_sum.assign(P, 0.0);
  out->alpha.assign(P, 0.0);
  out->intensity_sum.assign(P, 0.0);
  pool.ParallelFor(static_cast<int64_t>(p.tiles_x) * p.tiles_y, 1, [&](int64_t t0, int64_t t1, int) {
    double T[kTile * kTile], D[kTile * kTile], I[kTile * kTile];
    for (int64_t tile = t0; tile < t1; ++tile) {
      const int x0 = static_cast<int>(tile % p.tiles_x) * kTile, y0 = static_cast<int>(tile / p.tiles_x) * kTile;
      const int rows = std::min(kTile, B - y0), cols = std::min(kTile, W - x0);
      BlendTileRef(splats.data(), tile_ids.data(), tile_offsets[tile], tile_offsets[tile + 1], x0, y0, rows, cols,
                   T, D, I, static_cast<int32_t*>(nullptr));
      for (int r = 0; r < rows; ++r) {
        for (int c = 0; c < cols; ++c) {
          const size_t pix = static_cast<size_t>(y0 + r) * W + x0 + c;
          out->alpha[pix] = 1.0 - T[r * kTile + c];
          out->range_sum[pix] = D[r * kTile + c];
          out->intensity_sum[pix] = I[r * kTile + c];
        }
      }
    }
  });
  if (!upstream || !grads) return absl::OkStatus();
  LidarBackwardView<double> view;
  view.splats = splats.data();
  view.splat_gauss = gauss.data();
  view.tile_offsets = tile_offsets.data();
  view.tile_ids = tile_ids.data();
  view.beams = B;
  view.columns = W;
  view.tiles_x = p.tiles_x;
  view.tiles_y = p.tiles_y;
  view.num_gaussians = n;
  LidarBackwardScratch<double> bwd_scratch;
  std::vector<double> splat_grads;
  BlendBackward(pool, view, *upstream, /*deterministic=*/true, &bwd_scratch, &splat_grads);
  ProjectBackward(pool, p, soa, refl, nullptr, splat_grads, grads);
  return absl::OkStatus();
}

}  // namespace streetsim
