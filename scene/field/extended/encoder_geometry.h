// The spatial encoder's geometric inputs per Gaussian (method.md section 2 item 1) and their
// backward to the canonical parameters: opacity sigmoid(logit) and the 6 unique entries of
// Σ = R S Sᵀ Rᵀ (R from the normalised quaternion (w, x, y, z), S = diag(exp(log-scales))), in the
// order (Σ00, Σ01, Σ02, Σ11, Σ12, Σ22).
#pragma once

#include <cmath>

namespace streetsim::field::internal {

template <typename T>
struct Rotation {
  T q[4];     // normalised (w, x, y, z)
  T inv = 0;  // 1 / |q| (0 for a zero quaternion: Σ = 0, no gradient)
  T R[3][3];
};

template <typename T>
inline Rotation<T> MakeRotation(const T* quat) {
  Rotation<T> r;
  const T n2 = quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3];
  r.inv = n2 > T(0) ? T(1) / std::sqrt(n2) : T(0);
  for (int k = 0; k < 4; ++k) r.q[k] = quat[k] * r.inv;
  const T w = r.q[0], x = r.q[1], y = r.q[2], z = r.q[3];
  r.R[0][0] = 1 - 2 * (y * y + z * z), r.R[0][1] = 2 * (x * y - w * z), r.R[0][2] = 2 * (x * z + w * y);
  r.R[1][0] = 2 * (x * y + w * z), r.R[1][1] = 1 - 2 * (x * x + z * z), r.R[1][2] = 2 * (y * z - w * x);
  r.R[2][0] = 2 * (x * z - w * y), r.R[2][1] = 2 * (y * z + w * x), r.R[2][2] = 1 - 2 * (x * x + y * y);
  return r;
}

inline constexpr int kSigmaIndex[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};

// out[0] = opacity, out[1..6] = vec Σ.
template <typename T>
inline void GeometryInputs(T opacity_logit, const T* log_scale, const T* quat, T* out) {
  out[0] = T(1) / (T(1) + std::exp(-opacity_logit));
  const Rotation<T> r = MakeRotation(quat);
  T M[3][3];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) M[i][k] = r.R[i][k] * std::exp(log_scale[k]);
  for (int e = 0; e < 6; ++e) {
    const int i = kSigmaIndex[e][0], j = kSigmaIndex[e][1];
    out[1 + e] = M[i][0] * M[j][0] + M[i][1] * M[j][1] + M[i][2] * M[j][2];
  }
}

// Given g[0] = dL/dopacity, g[1..6] = dL/dvec Σ: adds dL/dlogit, dL/dlog-scale, dL/dquat.
template <typename T>
inline void GeometryInputsBackward(T opacity_logit, const T* log_scale, const T* quat, const T* g, T* d_logit,
                                   T* d_log_scale, T* d_quat) {
  const T sig = T(1) / (T(1) + std::exp(-opacity_logit));
  if (d_logit) *d_logit += g[0] * sig * (T(1) - sig);
  const Rotation<T> r = MakeRotation(quat);
  T s[3], M[3][3];
  for (int k = 0; k < 3; ++k) s[k] = std::exp(log_scale[k]);
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) M[i][k] = r.R[i][k] * s[k];
  // Σ = M Mᵀ: dL/dM = (G + Gᵀ) M with G holding each vec entry's gradient at its (i, j).
  T G2[3][3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
  for (int e = 0; e < 6; ++e) {
    const int i = kSigmaIndex[e][0], j = kSigmaIndex[e][1];
    G2[i][j] += g[1 + e];
    G2[j][i] += g[1 + e];
  }
  T dM[3][3];
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) dM[i][k] = G2[i][0] * M[0][k] + G2[i][1] * M[1][k] + G2[i][2] * M[2][k];
  T dR[3][3];
  for (int k = 0; k < 3; ++k) {
    T ds = 0;
    for (int i = 0; i < 3; ++i) {
      ds += dM[i][k] * r.R[i][k];
      dR[i][k] = dM[i][k] * s[k];
    }
    if (d_log_scale) d_log_scale[k] += ds * s[k];
  }
  if (!d_quat) return;
  const T w = r.q[0], x = r.q[1], y = r.q[2], z = r.q[3];
  T dq[4];
  dq[0] = 2 * (-z * dR[0][1] + y * dR[0][2] + z * dR[1][0] - x * dR[1][2] - y * dR[2][0] + x * dR[2][1]);
  dq[1] = 2 * (y * dR[0][1] + z * dR[0][2] + y * dR[1][0] - 2 * x * dR[1][1] - w * dR[1][2] + z * dR[2][0] +
               w * dR[2][1] - 2 * x * dR[2][2]);
  dq[2] = 2 * (-2 * y * dR[0][0] + x * dR[0][1] + w * dR[0][2] + x * dR[1][0] + z * dR[1][2] - w * dR[2][0] +
               z * dR[2][1] - 2 * y * dR[2][2]);
  dq[3] = 2 * (-2 * z * dR[0][0] - w * dR[0][1] + x * dR[0][2] + w * dR[1][0] - 2 * z * dR[1][1] + y * dR[1][2] +
               x * dR[2][0] + y * dR[2][1]);
  // Through the normalisation q̂ = q / |q|.
  const T dot = dq[0] * r.q[0] + dq[1] * r.q[1] + dq[2] * r.q[2] + dq[3] * r.q[3];
  for (int k = 0; k < 4; ++k) d_quat[k] += (dq[k] - r.q[k] * dot) * r.inv;
}

}  // namespace streetsim::field::internal
