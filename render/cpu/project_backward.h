// Backward of the per-Gaussian projection (render/common/projection_math.h: ProjectGaussian):
// dL/d(splat: mean2D, conic, opacity, rgb, depth) -> dL/d(raw parameters: mean, log-scale,
// quaternion, opacity logit, SH). Templated on the scalar type (float for training, double as the
// gradient-check reference); straight-line, branch-free code so that a loop over Gaussians
// calling it can vectorise.
//
// Chain: conic <- cov2D = P P^T (+0.3 low-pass) <- P = T M, T = J W, M = R S <- (quaternion, scale);
// J (EWA Jacobian, with its frustum clamp) <- camera-space mean <- world mean; mean2D <- camera
// mean; rgb <- SH basis(direction(mean - camera centre)) and SH coefficients.
#pragma once

#include <algorithm>
#include <cmath>

#include "render/common/projection_backward_math.h"
#include "render/common/projection_math.h"

namespace streetsim::cpu {

// dL/d of one projected splat (what the blend backward accumulates per Gaussian).
enum SplatGradIndex { kGx = 0, kGy, kGa, kGb, kGc, kGo, kGr, kGg, kGbl, kGdepth, kSplatGradSize };

template <typename Real>
struct ParamGrads {
  Real mean[3];
  Real log_scale[3];
  Real quat[4];
  Real logit;
  Real sh[16 * 3];  // [k*3 + c]
  Real radius;      // 3DGS screen radius ceil(3 sqrt(lambda_max)) (not a gradient)
};

// Derivatives of the real SH basis (projection::ShBasis) w.r.t. the unit direction (x, y, z),
// contracted with dL/dbasis: returns dL/d(x, y, z) treating them as independent.
template <typename Real>
[[gnu::always_inline]] inline void ShBasisBackward(int degree, Real x, Real y, Real z, const Real* d_basis, Real* d_dir) {
  using projection::kShC1;
  using projection::kShC2;
  using projection::kShC3;
  Real gx = 0, gy = 0, gz = 0;
  if (degree >= 1) {
    gy += Real(-kShC1) * d_basis[1];
    gz += Real(kShC1) * d_basis[2];
    gx += Real(-kShC1) * d_basis[3];
  }
  if (degree >= 2) {
    const Real c0 = Real(kShC2[0]), c1 = Real(kShC2[1]), c2 = Real(kShC2[2]), c3 = Real(kShC2[3]),
               c4 = Real(kShC2[4]);
    // b4 = c0 xy; b5 = c1 yz; b6 = c2 (2zz - xx - yy); b7 = c3 xz; b8 = c4 (xx - yy)
    gx += d_basis[4] * c0 * y + d_basis[6] * c2 * (-2 * x) + d_basis[7] * c3 * z + d_basis[8] * c4 * (2 * x);
    gy += d_basis[4] * c0 * x + d_basis[5] * c1 * z + d_basis[6] * c2 * (-2 * y) + d_basis[8] * c4 * (-2 * y);
    gz += d_basis[5] * c1 * y + d_basis[6] * c2 * (4 * z) + d_basis[7] * c3 * x;
  }
  if (degree >= 3) {
    const Real xx = x * x, yy = y * y, zz = z * z;
    const Real k0 = Real(kShC3[0]), k1 = Real(kShC3[1]), k2 = Real(kShC3[2]), k3 = Real(kShC3[3]),
               k4 = Real(kShC3[4]), k5 = Real(kShC3[5]), k6 = Real(kShC3[6]);
    // b9  = k0 y (3xx - yy)
    gx += d_basis[9] * k0 * (6 * x * y);
    gy += d_basis[9] * k0 * (3 * xx - 3 * yy);
    // b10 = k1 x y z
    gx += d_basis[10] * k1 * y * z;
    gy += d_basis[10] * k1 * x * z;
    gz += d_basis[10] * k1 * x * y;
    // b11 = k2 y (4zz - xx - yy)
    gx += d_basis[11] * k2 * y * (-2 * x);
    gy += d_basis[11] * k2 * (4 * zz - xx - 3 * yy);
    gz += d_basis[11] * k2 * y * (8 * z);
    // b12 = k3 z (2zz - 3xx - 3yy)
    gx += d_basis[12] * k3 * z * (-6 * x);
    gy += d_basis[12] * k3 * z * (-6 * y);
    gz += d_basis[12] * k3 * (6 * zz - 3 * xx - 3 * yy);
    // b13 = k4 x (4zz - xx - yy)
    gx += d_basis[13] * k4 * (4 * zz - 3 * xx - yy);
    gy += d_basis[13] * k4 * x * (-2 * y);
    gz += d_basis[13] * k4 * x * (8 * z);
    // b14 = k5 z (xx - yy)
    gx += d_basis[14] * k5 * z * (2 * x);
    gy += d_basis[14] * k5 * z * (-2 * y);
    gz += d_basis[14] * k5 * (xx - yy);
    // b15 = k6 x (xx - 3yy)
    gx += d_basis[15] * k6 * (3 * xx - 3 * yy);
    gy += d_basis[15] * k6 * x * (-6 * y);
  }
  d_dir[0] = gx;
  d_dir[1] = gy;
  d_dir[2] = gz;
}

// Backward of ProjectGaussian for a visible Gaussian, in two parts: the geometry (2D mean, conic,
// opacity, depth -> mean, log-scale, quaternion, logit, radius; writes out->mean) and the colour
// (rgb -> SH coefficients and the mean through the view direction; adds to out->mean). `g` holds
// dL/d(splat) (SplatGradIndex). The forward is recomputed here (cheaper than storing its
// intermediates). The vectorised path (project_backward_simd.inc) runs the two parts as two
// loops over a chunk of Gaussians; the colour part takes the SH degree as a template parameter
// so that its loops unroll completely there.
// always_inline: too big for GCC's own inlining limits, and a call inside the vectorised loop
// stops it vectorising.
template <typename Real>
[[gnu::always_inline]] inline void ProjectGaussianBackwardGeometry(const projection::CameraParams<Real>& cam, const Real* mean,
                                            const Real* log_scale, const Real* quat, Real opacity_logit,
                                            const Real* g, ParamGrads<Real>* out) {
  using std::exp;
  using std::sqrt;
  const Real* W = cam.R_cam_from_world;
  const Real px = W[0] * mean[0] + W[1] * mean[1] + W[2] * mean[2] + cam.t_cam_from_world[0];
  const Real py = W[3] * mean[0] + W[4] * mean[1] + W[5] * mean[2] + cam.t_cam_from_world[1];
  const Real pz = W[6] * mean[0] + W[7] * mean[1] + W[8] * mean[2] + cam.t_cam_from_world[2];
  const Real opacity = Real(1) / (Real(1) + exp(-opacity_logit));

  // Rotation from the normalised quaternion.
  const Real qn2 = quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3];
  const Real qinv = Real(1) / sqrt(qn2);
  const Real qw = quat[0] * qinv, qx = quat[1] * qinv, qy = quat[2] * qinv, qz = quat[3] * qinv;
  Real R[9];
  R[0] = 1 - 2 * (qy * qy + qz * qz); R[1] = 2 * (qx * qy - qw * qz);     R[2] = 2 * (qx * qz + qw * qy);
  R[3] = 2 * (qx * qy + qw * qz);     R[4] = 1 - 2 * (qx * qx + qz * qz); R[5] = 2 * (qy * qz - qw * qx);
  R[6] = 2 * (qx * qz - qw * qy);     R[7] = 2 * (qy * qz + qw * qx);     R[8] = 1 - 2 * (qx * qx + qy * qy);
  const Real s[3] = {exp(log_scale[0]), exp(log_scale[1]), exp(log_scale[2])};
  Real M[9];
  projection::ScaledRotation(R, s, M);

  const Real inv_z = Real(1) / pz;
  const Real tan_half_x = Real(0.5) * Real(cam.width) / cam.fx;
  const Real tan_half_y = Real(0.5) * Real(cam.height) / cam.fy;
  const Real lim_x_pos = (Real(cam.width) - cam.cx) / cam.fx + Real(projection::Limits::kFrustumMargin) * tan_half_x;
  const Real lim_x_neg = cam.cx / cam.fx + Real(projection::Limits::kFrustumMargin) * tan_half_x;
  const Real lim_y_pos = (Real(cam.height) - cam.cy) / cam.fy + Real(projection::Limits::kFrustumMargin) * tan_half_y;
  const Real lim_y_neg = cam.cy / cam.fy + Real(projection::Limits::kFrustumMargin) * tan_half_y;
  const Real ux = px * inv_z, uy = py * inv_z;
  const Real ux_c = std::min(lim_x_pos, std::max(-lim_x_neg, ux));
  const Real uy_c = std::min(lim_y_pos, std::max(-lim_y_neg, uy));
  const Real x_free = (ux == ux_c) ? Real(1) : Real(0);  // clamp inactive: derivative passes
  const Real y_free = (uy == uy_c) ? Real(1) : Real(0);
  const Real j00 = cam.fx * inv_z, j02 = -cam.fx * ux_c * inv_z;
  const Real j11 = cam.fy * inv_z, j12 = -cam.fy * uy_c * inv_z;
  const Real T0[3] = {j00 * W[0] + j02 * W[6], j00 * W[1] + j02 * W[7], j00 * W[2] + j02 * W[8]};
  const Real T1[3] = {j11 * W[3] + j12 * W[6], j11 * W[4] + j12 * W[7], j11 * W[5] + j12 * W[8]};
  const projection::Covariance2D<Real> cov =
      projection::ProjectCovariance(T0, T1, M, Real(projection::Limits::kLowPassPx));
  const Real cxx = cov.cxx, cxy = cov.cxy, cyy = cov.cyy, det = cov.det;
  const Real inv_det = Real(1) / det;

  const Real mid = Real(0.5) * (cxx + cyy);
  const Real lambda_max = mid + sqrt(std::max(Real(0.1), mid * mid - det));
  out->radius = std::ceil(Real(3) * sqrt(lambda_max));

  // conic -> 2D covariance -> T, Sigma -> M -> R, s -> quaternion.
  Real dT0[3], dT1[3];
  const projection::CovarianceChain<Real> chain{T0,  T1,  cov.p0, cov.p1, M,  s,  cxx, cxy, cyy,
                                                inv_det, Real(projection::Limits::kLowPassPx), qw, qx, qy, qz, qinv};
  projection::CovarianceChainBackward(chain, g[kGa], g[kGb], g[kGc], dT0, dT1, out->quat, out->log_scale);

  // T = J W -> J entries.
  const Real dj00 = dT0[0] * W[0] + dT0[1] * W[1] + dT0[2] * W[2];
  const Real dj02 = dT0[0] * W[6] + dT0[1] * W[7] + dT0[2] * W[8];
  const Real dj11 = dT1[0] * W[3] + dT1[1] * W[4] + dT1[2] * W[5];
  const Real dj12 = dT1[0] * W[6] + dT1[1] * W[7] + dT1[2] * W[8];
  // j00 = fx/pz, j02 = -fx ux_c/pz, ux_c = clamp(px/pz).
  Real dpx = 0, dpy = 0, dpz = g[kGdepth];
  dpz += -dj00 * cam.fx * inv_z * inv_z + dj02 * cam.fx * ux_c * inv_z * inv_z;
  dpz += -dj11 * cam.fy * inv_z * inv_z + dj12 * cam.fy * uy_c * inv_z * inv_z;
  const Real d_uxc = -dj02 * cam.fx * inv_z * x_free;
  const Real d_uyc = -dj12 * cam.fy * inv_z * y_free;
  // Screen position u = fx px/pz + cx: together with the clamp terms, d(px/pz).
  const Real d_ux = d_uxc + g[kGx] * cam.fx;
  const Real d_uy = d_uyc + g[kGy] * cam.fy;
  dpx += d_ux * inv_z;
  dpz += -d_ux * px * inv_z * inv_z;
  dpy += d_uy * inv_z;
  dpz += -d_uy * py * inv_z * inv_z;
  // p = W mean + t.
  for (int k = 0; k < 3; ++k) out->mean[k] = W[0 * 3 + k] * dpx + W[1 * 3 + k] * dpy + W[2 * 3 + k] * dpz;

  out->logit = g[kGo] * opacity * (Real(1) - opacity);
}

template <typename Real, int kDegree>
[[gnu::always_inline]] inline void ProjectGaussianBackwardColour(const projection::CameraParams<Real>& cam, const Real* mean,
                                          const Real* sh, const Real* g, ParamGrads<Real>* out) {
  using std::sqrt;
  constexpr int sh_degree = kDegree;
  // Colour: rgb_c = max(sum_k basis_k sh_kc + 0.5, 0).
  const Real dir[3] = {mean[0] - cam.cam_center_world[0], mean[1] - cam.cam_center_world[1],
                       mean[2] - cam.cam_center_world[2]};
  const Real inv_len = Real(1) / sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
  const Real ux3 = dir[0] * inv_len, uy3 = dir[1] * inv_len, uz3 = dir[2] * inv_len;
  Real basis[16];
  projection::ShBasis(sh_degree, ux3, uy3, uz3, basis);
  constexpr int K = (sh_degree + 1) * (sh_degree + 1);
  Real dv[3];
#pragma GCC unroll 3
  for (int c = 0; c < 3; ++c) {
    Real v = 0;
#pragma GCC unroll 16
    for (int k = 0; k < K; ++k) v += basis[k] * sh[k * 3 + c];
    dv[c] = (v + Real(0.5) > Real(0)) ? g[kGr + c] : Real(0);
  }
  Real d_basis[16];
#pragma GCC unroll 16
  for (int k = 0; k < K; ++k) {
    d_basis[k] = sh[k * 3 + 0] * dv[0] + sh[k * 3 + 1] * dv[1] + sh[k * 3 + 2] * dv[2];
#pragma GCC unroll 3
    for (int c = 0; c < 3; ++c) out->sh[k * 3 + c] = basis[k] * dv[c];
  }
  if constexpr (sh_degree > 0) {
    Real d_unit[3];
    ShBasisBackward(sh_degree, ux3, uy3, uz3, d_basis, d_unit);
    const Real dot = ux3 * d_unit[0] + uy3 * d_unit[1] + uz3 * d_unit[2];
    out->mean[0] += (d_unit[0] - ux3 * dot) * inv_len;
    out->mean[1] += (d_unit[1] - uy3 * dot) * inv_len;
    out->mean[2] += (d_unit[2] - uz3 * dot) * inv_len;
  }
}

template <typename Real>
inline void ProjectGaussianBackward(const projection::CameraParams<Real>& cam, const Real* mean,
                                    const Real* log_scale, const Real* quat, Real opacity_logit,
                                    const Real* sh, int sh_degree, const Real* g,
                                    ParamGrads<Real>* out) {
  ProjectGaussianBackwardGeometry<Real>(cam, mean, log_scale, quat, opacity_logit, g, out);
  switch (sh_degree) {
    case 0: ProjectGaussianBackwardColour<Real, 0>(cam, mean, sh, g, out); break;
    case 1: ProjectGaussianBackwardColour<Real, 1>(cam, mean, sh, g, out); break;
    case 2: ProjectGaussianBackwardColour<Real, 2>(cam, mean, sh, g, out); break;
    default: ProjectGaussianBackwardColour<Real, 3>(cam, mean, sh, g, out); break;
  }
}

}  // namespace streetsim::cpu
