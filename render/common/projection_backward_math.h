// Backward of the shared covariance chain of a projected Gaussian, for the camera's (render/cpu)
// and the LiDAR's (render/lidar) projection backwards: conic -> 2D covariance cov = P P^T with
// P = T M (projection_math.h: ProjectCovariance) -> T and M = R diag(s) -> the normalised
// quaternion and the scales. Only the Jacobian J in T = J W differs between the sensors; each
// caller takes dT on through its own J.
#pragma once

namespace streetsim::projection {

// Forward values of the chain, as the caller computed them.
template <typename Real>
struct CovarianceChain {
  const Real* T0;  // rows of T = J W
  const Real* T1;
  const Real* P0;  // rows of P = T M (Covariance2D::p0, p1)
  const Real* P1;
  const Real* M;   // R diag(s), row-major, R the rotation of the normalised quaternion
  const Real* s;   // scales
  Real cxx, cxy, cyy;  // 2D covariance (low-pass included)
  Real inv_det;        // 1 / det(cov), from Covariance2D::det
  Real low_pass;
  Real qw, qx, qy, qz;
  Real qinv;  // 1 / |q| of the raw quaternion
};

// (ga, gb, gc): gradient of the conic (a, b, c) = (cyy, -cxy, cxx) / det. Writes dT0, dT1,
// d_quat (raw quaternion) and ds_times_s (= d loss / d log s, before any clamp of the caller).
// always_inline: inside the camera's vectorised loop a call would stop the vectoriser.
template <typename Real>
[[gnu::always_inline]] inline void CovarianceChainBackward(const CovarianceChain<Real>& f, Real ga, Real gb, Real gc,
                                                           Real* dT0, Real* dT1, Real* d_quat, Real* ds_times_s) {
  // dL/dcov = -C G C (C the conic, G = [[ga, gb/2], [gb/2, gc]]), so dL/dP = 2 dL/dcov P =
  // -2 C G W with W = C P. For a needle splat the long axis's column of P lies almost in C's
  // null space: C P computed as a product cancels (each term ~|p|/low_pass, the result
  // ~1/|p|), and so does the chain through dL/dcov, whose terms are ~|p|^2 times too large;
  // either way the gradients of the mean and the scales were noise or inf. W is computed through
  // adj(cov) P = (p1 x q + lp p0; q x p0 + lp p1) / det, q = p0 x p1 (the same identity as the
  // determinant's), in which no product of the long axis is subtracted from another.
  const Real inv_det = f.inv_det, lp = f.low_pass;
  const Real *T0 = f.T0, *T1 = f.T1, *P0 = f.P0, *P1 = f.P1, *M = f.M, *s = f.s;
  const Real ca = f.cyy * inv_det, cb = -f.cxy * inv_det, cc = f.cxx * inv_det;
  const Real q[3] = {P0[1] * P1[2] - P0[2] * P1[1], P0[2] * P1[0] - P0[0] * P1[2], P0[0] * P1[1] - P0[1] * P1[0]};
  const Real w0[3] = {(P1[1] * q[2] - P1[2] * q[1] + lp * P0[0]) * inv_det,
                      (P1[2] * q[0] - P1[0] * q[2] + lp * P0[1]) * inv_det,
                      (P1[0] * q[1] - P1[1] * q[0] + lp * P0[2]) * inv_det};
  const Real w1[3] = {(q[1] * P0[2] - q[2] * P0[1] + lp * P1[0]) * inv_det,
                      (q[2] * P0[0] - q[0] * P0[2] + lp * P1[1]) * inv_det,
                      (q[0] * P0[1] - q[1] * P0[0] + lp * P1[2]) * inv_det};
  Real dP0[3], dP1[3];
  for (int k = 0; k < 3; ++k) {
    const Real gw0 = ga * w0[k] + Real(0.5) * gb * w1[k];
    const Real gw1 = Real(0.5) * gb * w0[k] + gc * w1[k];
    dP0[k] = -2 * (ca * gw0 + cb * gw1);
    dP1[k] = -2 * (cb * gw0 + cc * gw1);
    // d/d log s_k = <dL/dcov, 2 p_k p_k^T> = -2 w_k^T G w_k (p_k, w_k: column k of P, W),
    // directly: through dM it would be dP . p_k, which cancels for the long axis.
    ds_times_s[k] = -2 * (w0[k] * gw0 + w1[k] * gw1);
  }
  // P = T M: dT = dP M^T, dM = T^T dP.
  for (int r = 0; r < 3; ++r) {
    dT0[r] = M[r * 3 + 0] * dP0[0] + M[r * 3 + 1] * dP0[1] + M[r * 3 + 2] * dP0[2];
    dT1[r] = M[r * 3 + 0] * dP1[0] + M[r * 3 + 1] * dP1[1] + M[r * 3 + 2] * dP1[2];
  }
  Real dM[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) dM[r * 3 + k] = T0[r] * dP0[k] + T1[r] * dP1[k];
  // M = R diag(s).
  Real dR[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) dR[r * 3 + c] = dM[r * 3 + c] * s[c];
  // R(q normalised) -> dq_n.
  const Real qw = f.qw, qx = f.qx, qy = f.qy, qz = f.qz;
  Real dqn[4];
  dqn[0] = 2 * (-qz * dR[1] + qy * dR[2] + qz * dR[3] - qx * dR[5] - qy * dR[6] + qx * dR[7]);
  dqn[1] = 2 * (qy * dR[1] + qz * dR[2] + qy * dR[3] - 2 * qx * dR[4] - qw * dR[5] + qz * dR[6] + qw * dR[7] -
                2 * qx * dR[8]);
  dqn[2] = 2 * (-2 * qy * dR[0] + qx * dR[1] + qw * dR[2] + qx * dR[3] + qz * dR[5] - qw * dR[6] + qz * dR[7] -
                2 * qy * dR[8]);
  dqn[3] = 2 * (-2 * qz * dR[0] - qw * dR[1] + qx * dR[2] + qw * dR[3] - 2 * qz * dR[4] + qy * dR[5] +
                qx * dR[6] + qy * dR[7]);
  // Normalisation: dq = (dqn - qn (qn . dqn)) / |q|.
  const Real qdot = qw * dqn[0] + qx * dqn[1] + qy * dqn[2] + qz * dqn[3];
  d_quat[0] = (dqn[0] - qw * qdot) * f.qinv;
  d_quat[1] = (dqn[1] - qx * qdot) * f.qinv;
  d_quat[2] = (dqn[2] - qy * qdot) * f.qinv;
  d_quat[3] = (dqn[3] - qz * qdot) * f.qinv;
}

}  // namespace streetsim::projection
