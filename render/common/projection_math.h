// Per-Gaussian projection math of the 3DGS forward pass, written once, templated on the scalar
// type. The cpu backend uses it directly (float for rendering, double as the reference for
// gradient checks); render/vulkan/shaders/project.comp mirrors it line for line, so a change here
// must be made there too (tests/render/backend_agreement_test.cc holds them together).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace streetsim::projection {

template <typename Real>
struct CameraParams {
  Real R_cam_from_world[9];  // row-major
  Real t_cam_from_world[3];
  Real cam_center_world[3];
  Real fx, fy, cx, cy;
  int width, height;
  int tiles_x, tiles_y;
};

// The projected splat a tile blends (one per visible Gaussian).
template <typename Real>
struct Splat {
  Real x, y;           // mean in pixels (OpenCV: pixel centres at integers)
  Real conic[3];       // inverse 2D covariance (a, b, c): power = -0.5(a dx^2 + c dy^2) - b dx dy
  Real opacity;        // sigmoid(logit)
  Real rgb[3];         // SH colour, +0.5, clamped at 0
  Real depth;          // camera z, metres
  // a c - b^2 = 1 / det(cov), taken from the covariance's determinant: a c - b^2 computed from
  // the conic cancels for a needle splat.
  Real det_conic;
};

struct TileRect {
  int x0, y0, x1, y1;  // [x0, x1) x [y0, y1) in tiles; empty when culled
  int count() const { return (x1 - x0) * (y1 - y0); }
};

inline constexpr double kShC0 = 0.28209479177387814;
inline constexpr double kShC1 = 0.4886025119029199;
inline constexpr double kShC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                    -1.0925484305920792, 0.5462742152960396};
inline constexpr double kShC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                                    0.3731763325901154,  -0.4570457994644658, 1.445305721320277,
                                    -0.5900435899266435};

// SH basis values for a unit direction (K = (degree+1)^2 of them).
template <typename Real>
inline void ShBasis(int degree, Real x, Real y, Real z, Real* basis) {
  basis[0] = Real(kShC0);
  if (degree < 1) return;
  basis[1] = Real(-kShC1) * y;
  basis[2] = Real(kShC1) * z;
  basis[3] = Real(-kShC1) * x;
  if (degree < 2) return;
  const Real xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  basis[4] = Real(kShC2[0]) * xy;
  basis[5] = Real(kShC2[1]) * yz;
  basis[6] = Real(kShC2[2]) * (Real(2) * zz - xx - yy);
  basis[7] = Real(kShC2[3]) * xz;
  basis[8] = Real(kShC2[4]) * (xx - yy);
  if (degree < 3) return;
  basis[9] = Real(kShC3[0]) * y * (Real(3) * xx - yy);
  basis[10] = Real(kShC3[1]) * xy * z;
  basis[11] = Real(kShC3[2]) * y * (Real(4) * zz - xx - yy);
  basis[12] = Real(kShC3[3]) * z * (Real(2) * zz - Real(3) * xx - Real(3) * yy);
  basis[13] = Real(kShC3[4]) * x * (Real(4) * zz - xx - yy);
  basis[14] = Real(kShC3[5]) * z * (xx - yy);
  basis[15] = Real(kShC3[6]) * x * (xx - Real(3) * yy);
}

// Rotation matrix (row-major) from an unnormalised quaternion (w, x, y, z).
template <typename Real>
inline void QuatToRotation(const Real* q_in, Real* R) {
  const Real inv = Real(1) / std::sqrt(q_in[0] * q_in[0] + q_in[1] * q_in[1] +
                                       q_in[2] * q_in[2] + q_in[3] * q_in[3]);
  const Real w = q_in[0] * inv, x = q_in[1] * inv, y = q_in[2] * inv, z = q_in[3] * inv;
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z);     R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z);     R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y);     R[7] = 2 * (y * z + w * x);     R[8] = 1 - 2 * (x * x + y * y);
}

// M = R diag(scale) (row-major), so that the 3D covariance is Sigma = M M^T.
template <typename Real>
[[gnu::always_inline]] inline void ScaledRotation(const Real* R, const Real* scale, Real* M) {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) M[r * 3 + c] = R[r * 3 + c] * scale[c];
}

// EWA: the 2D covariance cov = T Sigma T^T + low_pass I for the 2x3 map T = J W (rows T0, T1),
// and its determinant. Shared by the camera and the LiDAR projections.
//
// Computed through P = T M (cov = P P^T + low_pass I), not through Sigma: for a needle splat (one
// axis kilometres long, the others millimetres) cov is nearly rank one, and cxx cyy - cxy^2
// cancels in float to 0, a negative number or noise, so that the conic and its gradient
// overflowed. Lagrange's identity gives det = |p0 x p1|^2 + low_pass (|p0|^2 + |p1|^2) +
// low_pass^2: non-negative terms only, each accurate to rounding (M's columns are scaled one by
// one, so the cross product never subtracts two products of the long axis), never below
// low_pass^2.
template <typename Real>
struct Covariance2D {
  Real p0[3], p1[3];  // rows of P = T M
  Real cxx, cxy, cyy;  // low-pass included
  Real det;
};

template <typename Real>
[[gnu::always_inline]] inline Covariance2D<Real> ProjectCovariance(const Real* T0, const Real* T1, const Real* M,
                                                                    Real low_pass) {
  Covariance2D<Real> c;
  for (int k = 0; k < 3; ++k) {
    c.p0[k] = T0[0] * M[0 * 3 + k] + T0[1] * M[1 * 3 + k] + T0[2] * M[2 * 3 + k];
    c.p1[k] = T1[0] * M[0 * 3 + k] + T1[1] * M[1 * 3 + k] + T1[2] * M[2 * 3 + k];
  }
  const Real n0 = c.p0[0] * c.p0[0] + c.p0[1] * c.p0[1] + c.p0[2] * c.p0[2];
  const Real n1 = c.p1[0] * c.p1[0] + c.p1[1] * c.p1[1] + c.p1[2] * c.p1[2];
  const Real x0 = c.p0[1] * c.p1[2] - c.p0[2] * c.p1[1];
  const Real x1 = c.p0[2] * c.p1[0] - c.p0[0] * c.p1[2];
  const Real x2 = c.p0[0] * c.p1[1] - c.p0[1] * c.p1[0];
  c.cxx = n0 + low_pass;
  c.cxy = c.p0[0] * c.p1[0] + c.p0[1] * c.p1[1] + c.p0[2] * c.p1[2];
  c.cyy = n1 + low_pass;
  c.det = (x0 * x0 + x1 * x1 + x2 * x2) + low_pass * (n0 + n1) + low_pass * low_pass;
  return c;
}

// Converts a pixel extent to a tile rectangle clamped to the grid, computed in floating point
// first so that huge or non-finite extents cannot overflow an int.
template <typename Real>
inline TileRect PixelBoxToTiles(Real x_min, Real x_max, Real y_min, Real y_max, int tiles_x,
                                int tiles_y, int tile_size) {
  auto clampi = [](Real v, int hi) {
    v = std::min(std::max(v, Real(0)), Real(hi));
    return static_cast<int>(v);
  };
  const Real ts = Real(tile_size);
  // Tile t covers pixels [t*ts, (t+1)*ts); a splat touches tiles from floor(min/ts) to
  // floor(max/ts) inclusive.
  TileRect r;
  r.x0 = clampi(std::floor(x_min / ts), tiles_x);
  r.x1 = clampi(std::floor(x_max / ts) + 1, tiles_x);
  r.y0 = clampi(std::floor(y_min / ts), tiles_y);
  r.y1 = clampi(std::floor(y_max / ts) + 1, tiles_y);
  if (r.x1 <= r.x0 || r.y1 <= r.y0) r = TileRect{0, 0, 0, 0};
  return r;
}

struct Limits {
  static constexpr double kNearPlaneM = 0.2;
  static constexpr double kLowPassPx = 0.3;
  static constexpr double kFrustumMargin = 0.3;  // Jacobian clamp: 1.3 x the half field of view
  static constexpr double kMinAlpha = 1.0 / 255.0;
};

// Projects Gaussian i. Returns false (culled) when it is behind the near plane, degenerate,
// non-finite, too transparent to ever reach alpha 1/255, or touches no tile.
//
// The tile rectangle is the 3DGS 3-sigma square (radius = ceil(3 sqrt(lambda_max))) intersected
// with the box outside which o * G < 1/255 everywhere; dropping tiles outside that box never
// changes a pixel, it only saves work. `band_half_height` is the opacity box's half height in
// pixels, used by blenders to skip pixel rows a splat cannot reach.
template <typename Real>
inline bool ProjectGaussian(const CameraParams<Real>& cam, const Real* mean, const Real* log_scale,
                            const Real* quat, Real opacity_logit, const Real* sh, int sh_degree,
                            Splat<Real>* out, TileRect* rect, Real* band_half_height) {
  using std::exp;
  using std::sqrt;
  const Real* Rcw = cam.R_cam_from_world;
  const Real px = Rcw[0] * mean[0] + Rcw[1] * mean[1] + Rcw[2] * mean[2] + cam.t_cam_from_world[0];
  const Real py = Rcw[3] * mean[0] + Rcw[4] * mean[1] + Rcw[5] * mean[2] + cam.t_cam_from_world[1];
  const Real pz = Rcw[6] * mean[0] + Rcw[7] * mean[1] + Rcw[8] * mean[2] + cam.t_cam_from_world[2];
  if (!(pz > Real(Limits::kNearPlaneM))) return false;  // also rejects NaN

  const Real opacity = Real(1) / (Real(1) + exp(-opacity_logit));
  if (!(opacity * Real(255) > Real(1))) return false;  // o*G <= o < 1/255 everywhere

  Real R[9];
  QuatToRotation(quat, R);
  const Real s[3] = {exp(log_scale[0]), exp(log_scale[1]), exp(log_scale[2])};
  Real M[9];
  ScaledRotation(R, s, M);

  // EWA: J (2x3) of the perspective projection at the (clamped) camera-space mean.
  const Real inv_z = Real(1) / pz;
  const Real tan_half_x = Real(0.5) * Real(cam.width) / cam.fx;
  const Real tan_half_y = Real(0.5) * Real(cam.height) / cam.fy;
  const Real lim_x_pos = (Real(cam.width) - cam.cx) / cam.fx + Real(Limits::kFrustumMargin) * tan_half_x;
  const Real lim_x_neg = cam.cx / cam.fx + Real(Limits::kFrustumMargin) * tan_half_x;
  const Real lim_y_pos = (Real(cam.height) - cam.cy) / cam.fy + Real(Limits::kFrustumMargin) * tan_half_y;
  const Real lim_y_neg = cam.cy / cam.fy + Real(Limits::kFrustumMargin) * tan_half_y;
  const Real tx = pz * std::min(lim_x_pos, std::max(-lim_x_neg, px * inv_z));
  const Real ty = pz * std::min(lim_y_pos, std::max(-lim_y_neg, py * inv_z));
  const Real j00 = cam.fx * inv_z, j02 = -cam.fx * tx * inv_z * inv_z;
  const Real j11 = cam.fy * inv_z, j12 = -cam.fy * ty * inv_z * inv_z;
  // T = J W (2x3), W = R_cam_from_world.
  const Real T0[3] = {j00 * Rcw[0] + j02 * Rcw[6], j00 * Rcw[1] + j02 * Rcw[7], j00 * Rcw[2] + j02 * Rcw[8]};
  const Real T1[3] = {j11 * Rcw[3] + j12 * Rcw[6], j11 * Rcw[4] + j12 * Rcw[7], j11 * Rcw[5] + j12 * Rcw[8]};
  const Covariance2D<Real> cov = ProjectCovariance(T0, T1, M, Real(Limits::kLowPassPx));
  const Real cov_xx = cov.cxx, cov_xy = cov.cxy, cov_yy = cov.cyy, det = cov.det;
  if (!(det > Real(0)) || !std::isfinite(det)) return false;
  const Real inv_det = Real(1) / det;

  Splat<Real> sp;
  sp.x = cam.fx * px * inv_z + cam.cx;
  sp.y = cam.fy * py * inv_z + cam.cy;
  sp.conic[0] = cov_yy * inv_det;
  sp.conic[1] = -cov_xy * inv_det;
  sp.conic[2] = cov_xx * inv_det;
  sp.det_conic = inv_det;
  sp.opacity = opacity;
  sp.depth = pz;
  if (!std::isfinite(sp.x) || !std::isfinite(sp.y)) return false;

  const Real mid = Real(0.5) * (cov_xx + cov_yy);
  const Real lambda_max = mid + sqrt(std::max(Real(0.1), mid * mid - det));
  const Real radius = std::ceil(Real(3) * sqrt(lambda_max));
  // Where o * exp(-0.5 d^2) >= 1/255: d^2 <= 2 ln(255 o); the axis-aligned box of that ellipse has
  // half-widths sqrt(d^2 cov_xx), sqrt(d^2 cov_yy).
  const Real d2 = Real(2) * std::log(opacity * Real(255));
  const Real opacity_half_w = sqrt(d2 * cov_xx);
  const Real opacity_half_h = sqrt(d2 * cov_yy);
  const Real half_w = std::min(radius, opacity_half_w);
  const Real half_h = std::min(radius, opacity_half_h);
  *rect = PixelBoxToTiles(sp.x - half_w, sp.x + half_w, sp.y - half_h, sp.y + half_h, cam.tiles_x,
                          cam.tiles_y, 16);
  if (rect->count() == 0) return false;
  // Within a tile every pixel sees the splat (3DGS), so the row skip may only use the opacity
  // bound, never the 3-sigma radius.
  *band_half_height = opacity_half_h;

  // View-dependent colour.
  Real dir[3] = {mean[0] - cam.cam_center_world[0], mean[1] - cam.cam_center_world[1],
                 mean[2] - cam.cam_center_world[2]};
  const Real inv_len = Real(1) / sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
  Real basis[16];
  ShBasis(sh_degree, dir[0] * inv_len, dir[1] * inv_len, dir[2] * inv_len, basis);
  const int K = (sh_degree + 1) * (sh_degree + 1);
  for (int c = 0; c < 3; ++c) {
    Real v = 0;
    for (int k = 0; k < K; ++k) v += basis[k] * sh[k * 3 + c];
    sp.rgb[c] = std::max(v + Real(0.5), Real(0));
    // Finite SH coefficients can still sum to infinity; the blenders assume finite inputs.
    if (!std::isfinite(sp.rgb[c])) return false;
  }
  *out = sp;
  return true;
}

}  // namespace streetsim::projection
