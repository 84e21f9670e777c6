// The LiDAR renderer's scalar reference math, templated on the scalar type: float is the
// LidarRenderOptions::Kernel::kScalar path (what the vectorised kernels are tested against) and
// the backward's replay; double is the gradient-check reference (lidar_backward.h). One Gaussian
// or one pixel at a time, libm; docs/lidar.md states every rule.
#pragma once

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>

#include "render/common/projection_math.h"
#include "render/lidar/lidar_kernels.h"
#include "render/lidar/lidar_model.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {
class ThreadPool;
}

namespace streetsim::lidar {

// The structure-of-arrays copy of a (validated) store the LiDAR stages read.
void CopyToSoa(ThreadPool& pool, const GaussianStore& store, LidarSoa* soa);

// Per-sweep constants of the reference projection.
template <typename Real>
struct RefProjectParams {
  const LidarModel* model = nullptr;  // beam table (double, degrees) and column map
  const Real* pose_table = nullptr;   // [columns * kPoseStride] lidar_from_world per column
  bool rolling = false;
  Real near_m = 0, far_m = 0, cols_per_rad = 0;
  int columns = 0, beams = 0, tiles_x = 0, tiles_y = 0;
};

// One Gaussian's raw parameters (the store's layout), reflectance already clamped to [0, 1].
template <typename Real>
struct GaussianParams {
  Real mean[3], log_scale[3], quat[4], logit, refl;
};

// Gaussian i's parameters from the copy (reflectance: refl[i] clamped to [0, 1], 0.5 when null).
template <typename Real>
inline void GetGaussian(const LidarSoa& s, const float* refl, size_t i, GaussianParams<Real>* g) {
  g->mean[0] = s.mx[i];
  g->mean[1] = s.my[i];
  g->mean[2] = s.mz[i];
  g->log_scale[0] = s.ls0[i];
  g->log_scale[1] = s.ls1[i];
  g->log_scale[2] = s.ls2[i];
  g->quat[0] = s.qw[i];
  g->quat[1] = s.qx[i];
  g->quat[2] = s.qy[i];
  g->quat[3] = s.qz[i];
  g->logit = s.opacity_logit[i];
  g->refl = refl ? std::clamp(static_cast<Real>(refl[i]), Real(0), Real(1)) : Real(0.5);
}

// The column whose pose projects a Gaussian: its column coordinate u0 under the middle column's
// pose (no culls at this step), rounded and clamped: clamp(floor(u0 + 0.5), 0, columns - 1).
template <typename Real>
inline int PoseColumn(const RefProjectParams<Real>& p, const Real* mean) {
  if (!p.rolling) return p.columns / 2;
  const Real* e = p.pose_table + static_cast<size_t>(p.columns / 2) * kPoseStride;
  const Real px = e[0] * mean[0] + e[1] * mean[1] + e[2] * mean[2] + e[9];
  const Real py = e[3] * mean[0] + e[4] * mean[1] + e[5] * mean[2] + e[10];
  const double u0 = p.model->ColumnCoordinate(static_cast<double>(std::atan2(py, px)));
  return static_cast<int>(std::clamp(std::floor(u0 + 0.5), 0.0, static_cast<double>(p.columns - 1)));
}

// Projects a Gaussian with pose column col. False when culled (range outside (near, far), straight
// up/down, opacity <= 1/255, a non-positive or non-finite 2D covariance). half_w/half_h: the tile
// box's half extents (3-sigma square intersected with the opacity box).
template <typename Real>
inline bool ProjectGaussianRef(const RefProjectParams<Real>& p, int col, const GaussianParams<Real>& g,
                               LidarSplatT<Real>* sp, Real* half_w, Real* half_h) {
  using std::exp;
  using std::sqrt;
  const Real* e = p.pose_table + static_cast<size_t>(col) * kPoseStride;
  const Real* Rlw = e;
  const Real* m = g.mean;
  const Real px = Rlw[0] * m[0] + Rlw[1] * m[1] + Rlw[2] * m[2] + e[9];
  const Real py = Rlw[3] * m[0] + Rlw[4] * m[1] + Rlw[5] * m[2] + e[10];
  const Real pz = Rlw[6] * m[0] + Rlw[7] * m[1] + Rlw[8] * m[2] + e[11];
  const Real rho2 = px * px + py * py;
  const Real r2 = rho2 + pz * pz;
  const Real range = sqrt(r2);
  if (!(range > p.near_m) || !(range < p.far_m)) return false;  // also rejects NaN
  const Real rho = sqrt(rho2);
  if (!(rho > Real(1e-3) * range)) return false;  // straight up/down: no beam looks there
  const Real opacity = Real(1) / (Real(1) + exp(-g.logit));
  if (!(opacity * Real(255) > Real(1))) return false;

  Real R[9];
  projection::QuatToRotation(g.quat, R);
  const Real sc[3] = {exp(std::clamp(g.log_scale[0], Real(-30), Real(30))),
                      exp(std::clamp(g.log_scale[1], Real(-30), Real(30))),
                      exp(std::clamp(g.log_scale[2], Real(-30), Real(30)))};
  Real M[9];
  projection::ScaledRotation(R, sc, M);

  // u = (pi - atan2(y, x)) W / 2pi - 0.5:  du/dp = W/2pi (y, -x, 0) / rho^2
  // v = beam(atan2(z, rho)):              dv/dp = beam'(el) (-x z / rho, -y z / rho, rho) / r^2
  double dbeam = 0;
  const Real v = static_cast<Real>(p.model->BeamCoordinate(static_cast<double>(std::atan2(pz, rho)), &dbeam));
  const Real u = static_cast<Real>(p.model->ColumnCoordinate(static_cast<double>(std::atan2(py, px))));
  const Real ku = p.cols_per_rad / rho2;
  const Real kv = static_cast<Real>(dbeam) / r2;
  const Real J0[3] = {ku * py, -ku * px, Real(0)};
  const Real J1[3] = {-kv * px * pz / rho, -kv * py * pz / rho, kv * rho};
  Real T0[3], T1[3];  // T = J W, W = R_lidar_from_world
  for (int k = 0; k < 3; ++k) {
    T0[k] = J0[0] * Rlw[k] + J0[1] * Rlw[3 + k] + J0[2] * Rlw[6 + k];
    T1[k] = J1[0] * Rlw[k] + J1[1] * Rlw[3 + k] + J1[2] * Rlw[6 + k];
  }
  const projection::Covariance2D<Real> cov = projection::ProjectCovariance(T0, T1, M, Real(kLowPassPx));
  const Real cxx = cov.cxx, cxy = cov.cxy, cyy = cov.cyy, det = cov.det;
  if (!(det > Real(0)) || !std::isfinite(det)) return false;
  const Real inv_det = Real(1) / det;

  sp->x = u;
  sp->y = v;
  sp->a = cyy * inv_det;
  sp->b = -cxy * inv_det;
  sp->c = cxx * inv_det;
  sp->det_conic = inv_det;
  sp->opacity = opacity;
  sp->range = range;
  sp->refl = g.refl;
  const Real mid = Real(0.5) * (cxx + cyy);
  const Real lambda_max = mid + sqrt(std::max(Real(0.1), mid * mid - det));
  const Real radius = std::ceil(Real(3) * sqrt(lambda_max));
  const Real d2 = Real(2) * std::log(opacity * Real(255));
  sp->op_w = sqrt(d2 * cxx);
  sp->op_h = sqrt(d2 * cyy);
  *half_w = std::min(radius, sp->op_w);
  *half_h = std::min(radius, sp->op_h);
  return std::isfinite(sp->x) && std::isfinite(sp->y) && std::isfinite(*half_w) && std::isfinite(*half_h);
}

// Finishes a projected splat: the image-row cull, tile rects, and the copy one turn away when it
// crosses the seam (the same projection, x shifted by +-columns); appends to out. lidar_simd.inc
// computes the same vectorised.
template <typename Real>
inline void FillSplat(int columns, int beams, int tiles_x, int tiles_y, const LidarSplatT<Real>& sp,
                      Real half_w, Real half_h, uint32_t gauss, LidarProjectOutT<Real>* out) {
  const int B = beams, W = columns;
  if (sp.y + half_h < Real(-0.5) || sp.y - half_h > Real(B) - Real(0.5)) return;
  auto rect_of = [&](Real x) {
    auto clampi = [](Real t, int hi) { return static_cast<int>(std::min(std::max(t, Real(0)), static_cast<Real>(hi))); };
    // Pixel c samples coordinate c; tile t holds pixels [16 t, 16 t + 16) (as the camera path).
    Rect r;
    r.x0 = clampi(std::floor((x - half_w) / kTile), tiles_x);
    r.x1 = clampi(std::floor((x + half_w) / kTile) + 1, tiles_x);
    r.y0 = clampi(std::floor((sp.y - half_h) / kTile), tiles_y);
    r.y1 = clampi(std::floor((sp.y + half_h) / kTile) + 1, tiles_y);
    if (r.x1 <= r.x0 || r.y1 <= r.y0) r = Rect{0, 0, 0, 0};
    return r;
  };
  const uint32_t key = std::bit_cast<uint32_t>(static_cast<float>(sp.range));
  auto append = [&](const Rect& r, Real x) {
    out->splats[out->count] = sp;
    out->splats[out->count].x = x;
    out->rects[out->count] = r;
    out->keys[out->count] = key;
    out->gauss[out->count] = gauss;
    ++out->count;
  };
  const Rect r = rect_of(sp.x);
  if (r.count() > 0) append(r, sp.x);
  // The seam behind the sensor: a splat reaching past either end of the columns is drawn again one
  // turn away (not when it spans more than half a turn: it would be drawn twice).
  if (half_w < Real(0.5) * W) {
    Real x2 = 0;
    bool wrap = false;
    if (sp.x - half_w < Real(-0.5)) { x2 = sp.x + W; wrap = true; }
    if (sp.x + half_w > Real(W) - Real(0.5)) { x2 = sp.x - W; wrap = true; }
    if (wrap) {
      const Rect r2 = rect_of(x2);
      if (r2.count() > 0) append(r2, x2);
    }
  }
}

// The pixels of a tile (origin x0, y0; rows x cols) inside a splat's opacity box: rows [r0, r1],
// columns [c0, c1] (tile-local; empty when r0 > r1 or c0 > c1). Outside it opacity * G < 1/255, an
// exact skip. Bounds clamped in floating point first so that huge boxes cannot overflow an int.
template <typename Real>
inline void OpacityBox(const LidarSplatT<Real>& s, int x0, int y0, int rows, int cols, int* r0, int* r1,
                       int* c0, int* c1) {
  auto lo = [](Real v, int origin) {
    return std::max(0, static_cast<int>(std::ceil(std::max(v - origin, Real(-1)))));
  };
  auto hi = [](Real v, int origin, int n) {
    return std::min(n - 1, static_cast<int>(std::floor(std::min(v - origin, static_cast<Real>(n)))));
  };
  *r0 = lo(s.y - s.op_h, y0);
  *r1 = hi(s.y + s.op_h, y0, rows);
  *c0 = lo(s.x - s.op_w, x0);
  *c1 = hi(s.x + s.op_w, x0, cols);
}

// One splat at one pixel: alpha (0 when skipped: power > 0 or alpha < 1/255), G = exp(power).
template <typename Real>
inline Real SplatAlpha(const LidarSplatT<Real>& s, Real dx, Real dy, Real* G) {
  const Real power = Real(-0.5) * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
  if (power > Real(0)) return Real(0);
  *G = std::exp(power);
  const Real alpha = std::min(Real(kMaxAlpha), s.opacity * *G);
  return alpha < Real(kMinAlpha) ? Real(0) : alpha;
}

constexpr uint32_t kPrefetchAhead = 16;

// The reference blend of one tile (front to back; only the pixels inside each splat's opacity box).
// Writes final transmittance T (positive), range_sum and intensity_sum of the tile's pixels; when
// last is not null, last[r * 16 + c] = the list position of the pixel's last contributor (-1: none).
template <typename Real>
inline void BlendTileRef(const LidarSplatT<Real>* splats, const uint32_t* tile_ids, uint32_t list_begin,
                         uint32_t list_end, int x0, int y0, int rows, int cols, Real* T, Real* D, Real* I,
                         int32_t* last) {
  int live = rows * cols;
  bool done[kTile * kTile];
  for (int p = 0; p < kTile * kTile; ++p) {
    T[p] = 1;
    D[p] = I[p] = 0;
    done[p] = false;
    if (last) last[p] = -1;
  }
  for (uint32_t j = list_begin; j < list_end && live > 0; ++j) {
    // The list's splats are scattered in memory: start the misses well ahead.
    if (j + kPrefetchAhead < list_end) __builtin_prefetch(&splats[tile_ids[j + kPrefetchAhead]]);
    const LidarSplatT<Real>& s = splats[tile_ids[j]];
    int r0, r1, c0, c1;
    OpacityBox(s, x0, y0, rows, cols, &r0, &r1, &c0, &c1);
    for (int r = r0; r <= r1; ++r) {
      const Real dy = s.y - static_cast<Real>(y0 + r);
      for (int c = c0; c <= c1; ++c) {
        const int p = r * kTile + c;
        if (done[p]) continue;
        Real G;
        const Real alpha = SplatAlpha(s, s.x - static_cast<Real>(x0 + c), dy, &G);
        if (alpha == Real(0)) continue;
        const Real test_T = T[p] * (Real(1) - alpha);
        if (test_T < Real(kMinTransmittance)) {
          done[p] = true;  // this splat is not added
          --live;
          continue;
        }
        const Real w = alpha * T[p];
        D[p] += w * s.range;
        I[p] += w * s.refl;
        T[p] = test_T;
        if (last) last[p] = static_cast<int32_t>(j - list_begin);
      }
    }
  }
}

}  // namespace streetsim::lidar
