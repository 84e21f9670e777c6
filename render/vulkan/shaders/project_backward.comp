// Projection backward: one thread per visible Gaussian (depth rank j < V), dL/d(splat) ->
// dL/d(raw parameters). Mirrors render/cpu/project_backward.h (ProjectGaussianBackward) operation
// for operation in float, recomputing the forward (project.comp) rather than storing it:
// conic <- cov2D = P P^T (+0.3 low-pass) <- P = T M, T = J W, M = R S <- (quaternion, scale);
// J (EWA Jacobian with its frustum clamp) and the screen position <- camera-space mean <- mean;
// rgb <- SH basis(direction(mean - camera centre)) and the SH coefficients.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;

layout(std430, binding = 0) readonly buffer Gaussians { vec4 gauss[]; };
layout(std430, binding = 1) readonly buffer Sh0 { float sh0[]; };
layout(std430, binding = 2) readonly buffer Sh1 { float sh1[]; };
layout(std430, binding = 3) readonly buffer Sh2 { float sh2[]; };
layout(std430, binding = 4) readonly buffer Sh3 { float sh3[]; };
layout(std430, binding = 5) readonly buffer SortedIds { uint sorted_ids[]; };  // rank -> id
layout(std430, binding = 6) readonly buffer Counts { uint counts[]; };
layout(std430, binding = 7) readonly buffer SplatGrads { vec4 splat_grads[]; };  // 3 per rank
layout(std430, binding = 8) writeonly buffer ParamGrads { vec4 param_grads[]; };  // 4 per id
layout(std430, binding = 9) writeonly buffer DSh0 { float dsh0[]; };
layout(std430, binding = 10) writeonly buffer DSh1 { float dsh1[]; };
layout(std430, binding = 11) writeonly buffer DSh2 { float dsh2[]; };
layout(std430, binding = 12) writeonly buffer DSh3 { float dsh3[]; };

layout(push_constant, std430) uniform Camera {
  float R[9];  // R_cam_from_world, row-major
  float t[3];  // t_cam_from_world
  float c[3];  // camera centre, world
  float fx, fy, cx, cy;
  int width, height, tiles_x, tiles_y;
  uint n;
  int sh_degree;
} cam;

// The scene's SH degree (one pipeline per degree; the push constant's sh_degree is not read).
layout(constant_id = 0) const int SH_DEGREE = 3;

float smin(float a, float b) { return (b < a) ? b : a; }
float smax(float a, float b) { return (a < b) ? b : a; }

const float kShC0 = 0.28209479177387814;
const float kShC1 = 0.4886025119029199;
const float kShC2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                -1.0925484305920792, 0.5462742152960396);
const float kShC3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                                0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                                -0.5900435899266435);

vec3 ShCoeff(uint i, uint K, uint k) {
  const uint g = k / SH_GROUP;
  const uint o = i * ShGroupFloats(K, g) + (k % SH_GROUP) * 3u;
  if (g == 0u) return vec3(sh0[o], sh0[o + 1u], sh0[o + 2u]);
  if (g == 1u) return vec3(sh1[o], sh1[o + 1u], sh1[o + 2u]);
  if (g == 2u) return vec3(sh2[o], sh2[o + 1u], sh2[o + 2u]);
  return vec3(sh3[o], sh3[o + 1u], sh3[o + 2u]);
}

void StoreDSh(uint i, uint K, uint k, vec3 d) {
  const uint g = k / SH_GROUP;
  const uint o = i * ShGroupFloats(K, g) + (k % SH_GROUP) * 3u;
  if (g == 0u) { dsh0[o] = d.x; dsh0[o + 1u] = d.y; dsh0[o + 2u] = d.z; }
  else if (g == 1u) { dsh1[o] = d.x; dsh1[o + 1u] = d.y; dsh1[o + 2u] = d.z; }
  else if (g == 2u) { dsh2[o] = d.x; dsh2[o + 1u] = d.y; dsh2[o + 2u] = d.z; }
  else { dsh3[o] = d.x; dsh3[o + 1u] = d.y; dsh3[o + 2u] = d.z; }
}

void main() {
  const uint j = linear_thread_id();
  if (j >= counts[COUNT_V]) return;
  const uint i = sorted_ids[j];
  const vec4 ga0 = splat_grads[3u * j], ga1 = splat_grads[3u * j + 1u],
             ga2 = splat_grads[3u * j + 2u];
  // SplatGradIndex: x, y, a, b | c, o, r, g | bl, depth.
  const float g_x = ga0.x, g_y = ga0.y, g_a = ga0.z, g_b = ga0.w, g_c = ga1.x, g_o = ga1.y;
  const vec3 g_rgb = vec3(ga1.z, ga1.w, ga2.x);
  const float g_depth = ga2.y;

  const vec4 g0 = gauss[3u * i], g1 = gauss[3u * i + 1u], q = gauss[3u * i + 2u];
  const vec3 mean = g0.xyz;
  float W[9];
  for (int k = 0; k < 9; ++k) W[k] = cam.R[k];
  const float px = W[0] * mean.x + W[1] * mean.y + W[2] * mean.z + cam.t[0];
  const float py = W[3] * mean.x + W[4] * mean.y + W[5] * mean.z + cam.t[1];
  const float pz = W[6] * mean.x + W[7] * mean.y + W[8] * mean.z + cam.t[2];
  const float opacity = 1.0 / (1.0 + exp(-g0.w));

  const float qn2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w;
  const float qinv = 1.0 / sqrt(qn2);
  const float qw = q.x * qinv, qx = q.y * qinv, qy = q.z * qinv, qz = q.w * qinv;
  float Rq[9];
  Rq[0] = 1.0 - 2.0 * (qy * qy + qz * qz); Rq[1] = 2.0 * (qx * qy - qw * qz); Rq[2] = 2.0 * (qx * qz + qw * qy);
  Rq[3] = 2.0 * (qx * qy + qw * qz); Rq[4] = 1.0 - 2.0 * (qx * qx + qz * qz); Rq[5] = 2.0 * (qy * qz - qw * qx);
  Rq[6] = 2.0 * (qx * qz - qw * qy); Rq[7] = 2.0 * (qy * qz + qw * qx); Rq[8] = 1.0 - 2.0 * (qx * qx + qy * qy);
  const float s[3] = float[3](exp(g1.x), exp(g1.y), exp(g1.z));
  float M[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) M[r * 3 + k] = Rq[r * 3 + k] * s[k];

  const float inv_z = 1.0 / pz;
  const float tan_half_x = 0.5 * float(cam.width) / cam.fx;
  const float tan_half_y = 0.5 * float(cam.height) / cam.fy;
  const float lim_x_pos = (float(cam.width) - cam.cx) / cam.fx + 0.3 * tan_half_x;
  const float lim_x_neg = cam.cx / cam.fx + 0.3 * tan_half_x;
  const float lim_y_pos = (float(cam.height) - cam.cy) / cam.fy + 0.3 * tan_half_y;
  const float lim_y_neg = cam.cy / cam.fy + 0.3 * tan_half_y;
  const float ux = px * inv_z, uy = py * inv_z;
  const float ux_c = smin(lim_x_pos, smax(-lim_x_neg, ux));
  const float uy_c = smin(lim_y_pos, smax(-lim_y_neg, uy));
  const float x_free = (ux == ux_c) ? 1.0 : 0.0;
  const float y_free = (uy == uy_c) ? 1.0 : 0.0;
  const float j00 = cam.fx * inv_z, j02 = -cam.fx * ux_c * inv_z;
  const float j11 = cam.fy * inv_z, j12 = -cam.fy * uy_c * inv_z;
  const vec3 T0 = vec3(j00 * W[0] + j02 * W[6], j00 * W[1] + j02 * W[7], j00 * W[2] + j02 * W[8]);
  const vec3 T1 = vec3(j11 * W[3] + j12 * W[6], j11 * W[4] + j12 * W[7], j11 * W[5] + j12 * W[8]);
  // ProjectCovariance (project.comp): cov = P P^T + 0.3 I, P = T M, det by Lagrange's identity.
  vec3 p0, p1;
  for (int k = 0; k < 3; ++k) {
    p0[k] = T0.x * M[k] + T0.y * M[3 + k] + T0.z * M[6 + k];
    p1[k] = T1.x * M[k] + T1.y * M[3 + k] + T1.z * M[6 + k];
  }
  const float n0 = dot(p0, p0), n1 = dot(p1, p1);
  const vec3 q3 = cross(p0, p1);
  const float cxx = n0 + 0.3;
  const float cxy = dot(p0, p1);
  const float cyy = n1 + 0.3;
  const float det = dot(q3, q3) + 0.3 * (n0 + n1) + 0.3 * 0.3;
  const float inv_det = 1.0 / det;
  const float mid = 0.5 * (cxx + cyy);
  const float lambda_max = mid + sqrt(smax(0.1, mid * mid - det));
  const float radius = ceil(3.0 * sqrt(lambda_max));

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
  const vec3 d_log_scale = -2.0 * (w0 * gw0 + w1 * gw1);
  vec3 dT0, dT1;
  for (int r = 0; r < 3; ++r) {
    dT0[r] = M[r * 3] * dP0.x + M[r * 3 + 1] * dP0.y + M[r * 3 + 2] * dP0.z;
    dT1[r] = M[r * 3] * dP1.x + M[r * 3 + 1] * dP1.y + M[r * 3 + 2] * dP1.z;
  }
  float dM[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) dM[r * 3 + k] = T0[r] * dP0[k] + T1[r] * dP1[k];
  float dR[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) dR[r * 3 + k] = dM[r * 3 + k] * s[k];
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

  const float dj00 = dT0.x * W[0] + dT0.y * W[1] + dT0.z * W[2];
  const float dj02 = dT0.x * W[6] + dT0.y * W[7] + dT0.z * W[8];
  const float dj11 = dT1.x * W[3] + dT1.y * W[4] + dT1.z * W[5];
  const float dj12 = dT1.x * W[6] + dT1.y * W[7] + dT1.z * W[8];
  float dpx = 0.0, dpy = 0.0, dpz = g_depth;
  dpz += -dj00 * cam.fx * inv_z * inv_z + dj02 * cam.fx * ux_c * inv_z * inv_z;
  dpz += -dj11 * cam.fy * inv_z * inv_z + dj12 * cam.fy * uy_c * inv_z * inv_z;
  const float d_uxc = -dj02 * cam.fx * inv_z * x_free;
  const float d_uyc = -dj12 * cam.fy * inv_z * y_free;
  const float d_ux = d_uxc + g_x * cam.fx;
  const float d_uy = d_uyc + g_y * cam.fy;
  dpx += d_ux * inv_z;
  dpz += -d_ux * px * inv_z * inv_z;
  dpy += d_uy * inv_z;
  dpz += -d_uy * py * inv_z * inv_z;
  vec3 d_mean;
  for (int k = 0; k < 3; ++k) d_mean[k] = W[k] * dpx + W[3 + k] * dpy + W[6 + k] * dpz;
  const float d_logit = g_o * opacity * (1.0 - opacity);

  // Colour: rgb = max(sum_k basis_k sh_k + 0.5, 0). The degree is a specialization constant and
  // every coefficient index a constant, so that nothing lives in indexed (scratch) arrays.
  const uint K = uint((SH_DEGREE + 1) * (SH_DEGREE + 1));
  const vec3 dir = mean - vec3(cam.c[0], cam.c[1], cam.c[2]);
  const float inv_len = 1.0 / sqrt(dot(dir, dir));
  const float x = dir.x * inv_len, y = dir.y * inv_len, z = dir.z * inv_len;
  const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const float b0 = kShC0;
  const float b1 = -kShC1 * y, b2 = kShC1 * z, b3 = -kShC1 * x;
  const float b4 = kShC2[0] * xy, b5 = kShC2[1] * yz, b6 = kShC2[2] * (2.0 * zz - xx - yy),
              b7 = kShC2[3] * xz, b8 = kShC2[4] * (xx - yy);
  const float b9 = kShC3[0] * y * (3.0 * xx - yy), b10 = kShC3[1] * xy * z,
              b11 = kShC3[2] * y * (4.0 * zz - xx - yy),
              b12 = kShC3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
              b13 = kShC3[4] * x * (4.0 * zz - xx - yy), b14 = kShC3[5] * z * (xx - yy),
              b15 = kShC3[6] * x * (xx - 3.0 * yy);
  vec3 vsum = b0 * ShCoeff(i, K, 0u);
  if (SH_DEGREE >= 1) vsum += b1 * ShCoeff(i, K, 1u) + b2 * ShCoeff(i, K, 2u) + b3 * ShCoeff(i, K, 3u);
  if (SH_DEGREE >= 2) {
    vsum += b4 * ShCoeff(i, K, 4u) + b5 * ShCoeff(i, K, 5u) + b6 * ShCoeff(i, K, 6u) +
            b7 * ShCoeff(i, K, 7u) + b8 * ShCoeff(i, K, 8u);
  }
  if (SH_DEGREE >= 3) {
    vsum += b9 * ShCoeff(i, K, 9u) + b10 * ShCoeff(i, K, 10u) + b11 * ShCoeff(i, K, 11u) +
            b12 * ShCoeff(i, K, 12u) + b13 * ShCoeff(i, K, 13u) + b14 * ShCoeff(i, K, 14u) +
            b15 * ShCoeff(i, K, 15u);
  }
  const vec3 dv = vec3(vsum.x + 0.5 > 0.0 ? g_rgb.x : 0.0, vsum.y + 0.5 > 0.0 ? g_rgb.y : 0.0,
                       vsum.z + 0.5 > 0.0 ? g_rgb.z : 0.0);
  // dL/dbasis_k = sh_k . dv and dL/dsh_k = basis_k dv.
#define SH_BWD(k, b) \
  const float db##k = dot(ShCoeff(i, K, uint(k)), dv); \
  StoreDSh(i, K, uint(k), b * dv);
  SH_BWD(0, b0)
  if (SH_DEGREE >= 1) {
    SH_BWD(1, b1) SH_BWD(2, b2) SH_BWD(3, b3)
    float gx = -kShC1 * db3, gy = -kShC1 * db1, gz = kShC1 * db2;
    if (SH_DEGREE >= 2) {
      SH_BWD(4, b4) SH_BWD(5, b5) SH_BWD(6, b6) SH_BWD(7, b7) SH_BWD(8, b8)
      gx += db4 * kShC2[0] * y + db6 * kShC2[2] * (-2.0 * x) + db7 * kShC2[3] * z +
            db8 * kShC2[4] * (2.0 * x);
      gy += db4 * kShC2[0] * x + db5 * kShC2[1] * z + db6 * kShC2[2] * (-2.0 * y) +
            db8 * kShC2[4] * (-2.0 * y);
      gz += db5 * kShC2[1] * y + db6 * kShC2[2] * (4.0 * z) + db7 * kShC2[3] * x;
      if (SH_DEGREE >= 3) {
        SH_BWD(9, b9) SH_BWD(10, b10) SH_BWD(11, b11) SH_BWD(12, b12) SH_BWD(13, b13)
        SH_BWD(14, b14) SH_BWD(15, b15)
        gx += db9 * kShC3[0] * (6.0 * x * y);
        gy += db9 * kShC3[0] * (3.0 * xx - 3.0 * yy);
        gx += db10 * kShC3[1] * y * z;
        gy += db10 * kShC3[1] * x * z;
        gz += db10 * kShC3[1] * x * y;
        gx += db11 * kShC3[2] * y * (-2.0 * x);
        gy += db11 * kShC3[2] * (4.0 * zz - xx - 3.0 * yy);
        gz += db11 * kShC3[2] * y * (8.0 * z);
        gx += db12 * kShC3[3] * z * (-6.0 * x);
        gy += db12 * kShC3[3] * z * (-6.0 * y);
        gz += db12 * kShC3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy);
        gx += db13 * kShC3[4] * (4.0 * zz - 3.0 * xx - yy);
        gy += db13 * kShC3[4] * x * (-2.0 * y);
        gz += db13 * kShC3[4] * x * (8.0 * z);
        gx += db14 * kShC3[5] * z * (2.0 * x);
        gy += db14 * kShC3[5] * z * (-2.0 * y);
        gz += db14 * kShC3[5] * (xx - yy);
        gx += db15 * kShC3[6] * (3.0 * xx - 3.0 * yy);
        gy += db15 * kShC3[6] * x * (-6.0 * y);
      }
    }
    const float d = x * gx + y * gy + z * gz;
    d_mean += vec3(gx - x * d, gy - y * d, gz - z * d) * inv_len;
  }

  param_grads[4u * i] = vec4(d_mean, d_logit);
  param_grads[4u * i + 1u] = vec4(d_log_scale, radius);
  param_grads[4u * i + 2u] = d_quat;
  param_grads[4u * i + 3u] = vec4(g_x, g_y, 0.0, 0.0);
}
