// Backward of the shared covariance chain of a projected Gaussian, for the camera's (render/cpu)
// and the LiDAR's (render/lidar) projection backwards: conic -> 2D covariance cov = T Sigma T^T
// -> T and Sigma = M M^T -> M = R diag(s) -> the normalised quaternion and the scales. Only the
// Jacobian J in T = J W differs between the sensors; each caller takes dT on through its own J.
#pragma once

namespace streetsim::projection {

// Forward values of the chain, as the caller computed them.
template <typename Real>
struct CovarianceChain {
  const Real* T0;  // rows of T = J W
  const Real* T1;
  const Real* S0;  // Sigma T0^T, Sigma T1^T
  const Real* S1;
  const Real* M;   // R diag(s), row-major
  const Real* R;   // rotation of the normalised quaternion (qw, qx, qy, qz)
  const Real* s;   // scales
  Real cxx, cxy, cyy;  // 2D covariance (low-pass included)
  Real inv_det;        // 1 / (cxx cyy - cxy^2)
  Real qw, qx, qy, qz;
  Real qinv;  // 1 / |q| of the raw quaternion
};

// (ga, gb, gc): gradient of the conic (a, b, c) = (cyy, -cxy, cxx) / det. Writes dT0, dT1,
// d_quat (raw quaternion) and ds_times_s (= d loss / d log s, before any clamp of the caller).
// always_inline: inside the camera's vectorised loop a call would stop the vectoriser.
template <typename Real>
[[gnu::always_inline]] inline void CovarianceChainBackward(const CovarianceChain<Real>& f, Real ga, Real gb, Real gc,
                                                           Real* dT0, Real* dT1, Real* d_quat, Real* ds_times_s) {
  const Real cxx = f.cxx, cxy = f.cxy, cyy = f.cyy, inv_det = f.inv_det;
  const Real inv_det2 = inv_det * inv_det;
  const Real d_cxx = -ga * cyy * cyy * inv_det2 + gb * cxy * cyy * inv_det2 + gc * (inv_det - cxx * cyy * inv_det2);
  const Real d_cyy = ga * (inv_det - cxx * cyy * inv_det2) + gb * cxy * cxx * inv_det2 - gc * cxx * cxx * inv_det2;
  const Real d_cxy = ga * 2 * cxy * cyy * inv_det2 + gb * (-inv_det - 2 * cxy * cxy * inv_det2) +
                     gc * 2 * cxy * cxx * inv_det2;

  // cov = T Sigma T^T: dT0 = 2 d_cxx S0 + d_cxy S1, dT1 = 2 d_cyy S1 + d_cxy S0;
  // dSigma (full, then symmetrised through M) = d_cxx T0T0^T + d_cxy T0T1^T + d_cyy T1T1^T.
  const Real *T0 = f.T0, *T1 = f.T1, *S0 = f.S0, *S1 = f.S1, *M = f.M, *R = f.R, *s = f.s;
  for (int k = 0; k < 3; ++k) {
    dT0[k] = 2 * d_cxx * S0[k] + d_cxy * S1[k];
    dT1[k] = 2 * d_cyy * S1[k] + d_cxy * S0[k];
  }
  Real dSig[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      dSig[r * 3 + c] = d_cxx * T0[r] * T0[c] + d_cxy * T0[r] * T1[c] + d_cyy * T1[r] * T1[c];
  // Sigma = M M^T: dM = (dSig + dSig^T) M.
  Real dM[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) {
      Real v = 0;
      for (int k = 0; k < 3; ++k) v += (dSig[r * 3 + k] + dSig[k * 3 + r]) * M[k * 3 + c];
      dM[r * 3 + c] = v;
    }
  // M = R diag(s).
  Real dR[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) dR[r * 3 + c] = dM[r * 3 + c] * s[c];
  for (int c = 0; c < 3; ++c) {
    const Real ds = dM[0 * 3 + c] * R[0 * 3 + c] + dM[1 * 3 + c] * R[1 * 3 + c] + dM[2 * 3 + c] * R[2 * 3 + c];
    ds_times_s[c] = ds * s[c];
  }
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
