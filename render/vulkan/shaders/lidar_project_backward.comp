// LiDAR projection backward: one thread per Gaussian, dL/d(splat terms) -> dL/d(raw parameters).
// Mirrors render/lidar/lidar_backward.cc (ProjectGaussianBackwardRef) in float, recomputing the
// forward as lidar_project.comp does (the pose table entry it used, read from its splat record;
// the same beam segment search and atan2), formulas in
// docs/lidar.md "Backward pass": conic <- 2D covariance P P^T (+0.3) <- P = T M, T = J W, M = R S
// <- (quaternion, log-scale); J (the spherical Jacobian, its beam segment fixed), u, v and the
// range <- sensor-frame mean <- mean. The pose column is a constant (not differentiated).
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

layout(local_size_x = WG_SIZE) in;

layout(std430, binding = 0) readonly buffer Gaussians { vec4 gauss[]; };
layout(std430, binding = 1) readonly buffer Table { float table[]; };
layout(std430, binding = 2) readonly buffer Reflectance { float refl[]; };
// Per Gaussian (lidar_blend_backward.glsl): (u, v, a, b), (c, opacity, range, reflectance).
layout(std430, binding = 3) readonly buffer SplatGrads { vec4 splat_grads[]; };
// Per Gaussian: (d mean xyz, d opacity logit), (d log-scale xyz, d reflectance), d quaternion.
layout(std430, binding = 4) writeonly buffer ParamGrads { vec4 param_grads[]; };
// The forward's splat records by Gaussian (lidar_common.glsl); [2].w: the pose table entry.
layout(std430, binding = 5) readonly buffer Splats { vec4 splats[]; };

layout(push_constant, std430) uniform Params {  // lidar_project.comp's
  uint n;
  int columns, beams, tiles_x, tiles_y;
  float near_m, far_m, cols_per_rad;
  uint pose_offset;
  uint rolling;
  uint has_refl;
} pc;

vec3 Transform(uint pose, vec3 m, out float R[9]) {
  const uint o = pc.pose_offset + pose * POSE_STRIDE;
  for (int k = 0; k < 9; ++k) R[k] = table[o + uint(k)];
  return vec3(R[0] * m.x + R[1] * m.y + R[2] * m.z + table[o + 9u],
              R[3] * m.x + R[4] * m.y + R[5] * m.z + table[o + 10u],
              R[6] * m.x + R[7] * m.y + R[8] * m.z + table[o + 11u]);
}

void main() {
  const uint i = linear_thread_id();
  if (i >= pc.n) return;
  const vec4 ga = splat_grads[2u * i], gb = splat_grads[2u * i + 1u];
  const float g_u = ga.x, g_v = ga.y, g_a = ga.z, g_b = ga.w;
  const float g_c = gb.x, g_o = gb.y, g_range = gb.z, g_refl = gb.w;
  if (ga == vec4(0.0) && gb == vec4(0.0)) {  // not drawn, or no gradient reached it
    param_grads[3u * i] = vec4(0.0);
    param_grads[3u * i + 1u] = vec4(0.0);
    param_grads[3u * i + 2u] = vec4(0.0);
    return;
  }
  const vec4 g0 = gauss[3u * i], g1 = gauss[3u * i + 1u], q = gauss[3u * i + 2u];
  const vec3 mean = g0.xyz;

  // A Gaussian with a gradient was drawn, so its splat record is this sweep's.
  float W[9];
  const vec3 p = Transform(uint(splats[3u * i + 2u].w), mean, W);
  const float px = p.x, py = p.y, pz = p.z;
  const float rho2 = px * px + py * py;
  const float r2 = rho2 + pz * pz;
  const float range = sqrt(r2);
  const float rho = sqrt(rho2);
  const float opacity = 1.0 / (1.0 + exp(-g0.w));

  const float qinv = 1.0 / sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
  const float qw = q.x * qinv, qx = q.y * qinv, qy = q.z * qinv, qz = q.w * qinv;
  float Rq[9];
  Rq[0] = 1.0 - 2.0 * (qy * qy + qz * qz); Rq[1] = 2.0 * (qx * qy - qw * qz); Rq[2] = 2.0 * (qx * qz + qw * qy);
  Rq[3] = 2.0 * (qx * qy + qw * qz); Rq[4] = 1.0 - 2.0 * (qx * qx + qz * qz); Rq[5] = 2.0 * (qy * qz - qw * qx);
  Rq[6] = 2.0 * (qx * qz - qw * qy); Rq[7] = 2.0 * (qy * qz + qw * qx); Rq[8] = 1.0 - 2.0 * (qx * qx + qy * qy);
  const vec3 ls = g1.xyz;
  const float s[3] = float[3](exp(clamp(ls.x, -30.0, 30.0)), exp(clamp(ls.y, -30.0, 30.0)),
                              exp(clamp(ls.z, -30.0, 30.0)));
  float M[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) M[r * 3 + k] = Rq[r * 3 + k] * s[k];

  // The beam segment of the mean's elevation (lidar_project.comp's search), its slope fixed.
  const float el = LidarAtan2(pz, rho);
  const int L = pc.beams - 2;
  int k = 0;
  for (int step = 1 << findMSB(max(L, 1)); step > 0; step >>= 1) {
    const int m = min(k + step, max(L, 1));
    k += (k + step <= L && table[m] > el) ? step : 0;
  }
  const float kb = table[pc.beams + k];
  const float cpr = pc.cols_per_rad;
  const float ku = cpr / rho2, kv = kb / r2;
  const vec3 J0 = vec3(ku * py, -ku * px, 0.0);
  const vec3 J1 = vec3(-kv * px * pz / rho, -kv * py * pz / rho, kv * rho);
  vec3 T0, T1;
  for (int c = 0; c < 3; ++c) {
    T0[c] = J0.x * W[c] + J0.y * W[3 + c] + J0.z * W[6 + c];
    T1[c] = J1.x * W[c] + J1.y * W[3 + c] + J1.z * W[6 + c];
  }
  // ProjectCovariance: cov = P P^T + 0.3 I, P = T M, det by Lagrange's identity.
  vec3 p0, p1;
  for (int c = 0; c < 3; ++c) {
    p0[c] = T0.x * M[c] + T0.y * M[3 + c] + T0.z * M[6 + c];
    p1[c] = T1.x * M[c] + T1.y * M[3 + c] + T1.z * M[6 + c];
  }
  const vec3 q3 = cross(p0, p1);
  const float cxx = dot(p0, p0) + 0.3;
  const float cxy = dot(p0, p1);
  const float cyy = dot(p1, p1) + 0.3;
  const float inv_det = 1.0 / (dot(q3, q3) + 0.3 * (dot(p0, p0) + dot(p1, p1)) + 0.3 * 0.3);

  // CovarianceChainBackward (render/common/projection_backward_math.h): dL/dP = -2 C G W with
  // W = C P = adj(cov) P / det through the cross products (no cancellation for needle splats),
  // and d/d log s_k = -2 w_k^T G w_k directly.
  const float ca = cyy * inv_det, cb = -cxy * inv_det, cc = cxx * inv_det;
  const vec3 w0 = (cross(p1, q3) + 0.3 * p0) * inv_det;
  const vec3 w1 = (cross(q3, p0) + 0.3 * p1) * inv_det;
  const vec3 gw0 = g_a * w0 + 0.5 * g_b * w1;
  const vec3 gw1 = 0.5 * g_b * w0 + g_c * w1;
  const vec3 dP0 = -2.0 * (ca * gw0 + cb * gw1);
  const vec3 dP1 = -2.0 * (cb * gw0 + cc * gw1);
  const vec3 ds_times_s = -2.0 * (w0 * gw0 + w1 * gw1);
  vec3 dT0, dT1;
  for (int r = 0; r < 3; ++r) {
    dT0[r] = M[r * 3] * dP0.x + M[r * 3 + 1] * dP0.y + M[r * 3 + 2] * dP0.z;
    dT1[r] = M[r * 3] * dP1.x + M[r * 3 + 1] * dP1.y + M[r * 3 + 2] * dP1.z;
  }
  float dM[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) dM[r * 3 + c] = T0[r] * dP0[c] + T1[r] * dP1[c];
  float dR[9];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) dR[r * 3 + c] = dM[r * 3 + c] * s[c];
  vec3 d_log_scale;
  for (int c = 0; c < 3; ++c) {
    d_log_scale[c] = (ls[c] > -30.0 && ls[c] < 30.0) ? ds_times_s[c] : 0.0;  // the forward's clamp
  }
  vec4 dqn;
  dqn.x = 2.0 * (-qz * dR[1] + qy * dR[2] + qz * dR[3] - qx * dR[5] - qy * dR[6] + qx * dR[7]);
  dqn.y = 2.0 * (qy * dR[1] + qz * dR[2] + qy * dR[3] - 2.0 * qx * dR[4] - qw * dR[5] + qz * dR[6] +
                 qw * dR[7] - 2.0 * qx * dR[8]);
  dqn.z = 2.0 * (-2.0 * qy * dR[0] + qx * dR[1] + qw * dR[2] + qx * dR[3] + qz * dR[5] - qw * dR[6] +
                 qz * dR[7] - 2.0 * qy * dR[8]);
  dqn.w = 2.0 * (-2.0 * qz * dR[0] - qw * dR[1] + qx * dR[2] + qw * dR[3] - 2.0 * qz * dR[4] +
                 qy * dR[5] + qx * dR[6] + qy * dR[7]);
  const vec4 qn = vec4(qw, qx, qy, qz);
  const vec4 d_quat = (dqn - qn * dot(qn, dqn)) * qinv;

  // T = J W -> J; J, u, v, range -> the sensor-frame mean p.
  vec3 dJ0, dJ1;
  for (int r = 0; r < 3; ++r) {
    dJ0[r] = dT0.x * W[r * 3] + dT0.y * W[r * 3 + 1] + dT0.z * W[r * 3 + 2];
    dJ1[r] = dT1.x * W[r * 3] + dT1.y * W[r * 3 + 1] + dT1.z * W[r * 3 + 2];
  }
  // u, v themselves: du/dp = J0, dv/dp = J1; range: p / |p|.
  vec3 dp = g_u * J0 + g_v * J1 + g_range * (p / range);
  const float inv_rho2 = 1.0 / rho2;
  // J00 = cpr py / rho2, J01 = -cpr px / rho2.
  dp.x += dJ0.x * (-2.0 * cpr * py * px * inv_rho2 * inv_rho2);
  dp.y += dJ0.x * (cpr * inv_rho2 - 2.0 * cpr * py * py * inv_rho2 * inv_rho2);
  dp.x += dJ0.y * (-cpr * inv_rho2 + 2.0 * cpr * px * px * inv_rho2 * inv_rho2);
  dp.y += dJ0.y * (2.0 * cpr * px * py * inv_rho2 * inv_rho2);
  // J10 = -kb px pz f, J11 = -kb py pz f, f = 1 / (rho r2): d ln f = -(p_xy / rho2 + 2 p / r2).
  const float f = 1.0 / (rho * r2);
  const float lfx = -(px * inv_rho2 + 2.0 * px / r2), lfy = -(py * inv_rho2 + 2.0 * py / r2);
  const float lfz = -2.0 * pz / r2;
  dp.x += dJ1.x * (-kb * pz * f * (1.0 + px * lfx));
  dp.y += dJ1.x * (-kb * px * pz * f * lfy);
  dp.z += dJ1.x * (-kb * px * f * (1.0 + pz * lfz));
  dp.x += dJ1.y * (-kb * py * pz * f * lfx);
  dp.y += dJ1.y * (-kb * pz * f * (1.0 + py * lfy));
  dp.z += dJ1.y * (-kb * py * f * (1.0 + pz * lfz));
  // J12 = kb rho / r2: d ln(rho / r2) = p_xy / rho2 - 2 p / r2.
  dp.x += dJ1.z * J1.z * (px * inv_rho2 - 2.0 * px / r2);
  dp.y += dJ1.z * J1.z * (py * inv_rho2 - 2.0 * py / r2);
  dp.z += dJ1.z * J1.z * (-2.0 * pz / r2);
  vec3 d_mean;  // p = W m + t
  for (int c = 0; c < 3; ++c) d_mean[c] = W[c] * dp.x + W[3 + c] * dp.y + W[6 + c] * dp.z;
  const float d_logit = g_o * opacity * (1.0 - opacity);
  // The forward clamps the reflectance to [0, 1]: no gradient through the clamp.
  const float r_in = pc.has_refl != 0u ? refl[i] : 0.5;
  const float d_refl = (r_in >= 0.0 && r_in <= 1.0) ? g_refl : 0.0;

  param_grads[3u * i] = vec4(d_mean, d_logit);
  param_grads[3u * i + 1u] = vec4(d_log_scale, d_refl);
  param_grads[3u * i + 2u] = d_quat;
}
