// Stage a: one thread per Gaussian. Mirrors ProjectGaussian() of render/common/projection_math.h
// operation for operation (float), so that both backends cull, bin and shade identically.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "common.glsl"

layout(local_size_x = WG_SIZE) in;

layout(std430, binding = 0) readonly buffer Gaussians { vec4 gauss[]; };
// SH coefficients k in [4g, 4g + 4) of every Gaussian live in group g (common.glsl).
layout(std430, binding = 1) readonly buffer Sh0 { float sh0[]; };
layout(std430, binding = 2) readonly buffer Sh1 { float sh1[]; };
layout(std430, binding = 3) readonly buffer Sh2 { float sh2[]; };
layout(std430, binding = 4) readonly buffer Sh3 { float sh3[]; };
layout(std430, binding = 5) writeonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 6) writeonly buffer Rects { uvec2 rects[]; };
layout(std430, binding = 7) writeonly buffer Flags { uint flags[]; };
layout(std430, binding = 8) writeonly buffer Touched { uint touched[]; };

layout(push_constant, std430) uniform Camera {
  float R[9];  // R_cam_from_world, row-major
  float t[3];  // t_cam_from_world
  float c[3];  // camera centre, world
  float fx, fy, cx, cy;
  int width, height, tiles_x, tiles_y;
  uint n;
  int sh_degree;
} cam;

// std::min / std::max exactly (their NaN behaviour included), not GLSL min/max.
float smin(float a, float b) { return (b < a) ? b : a; }
float smax(float a, float b) { return (a < b) ? b : a; }
bool finite(float v) { return !isnan(v) && !isinf(v); }

const float kShC0 = 0.28209479177387814;
const float kShC1 = 0.4886025119029199;
const float kShC2_0 = 1.0925484305920792, kShC2_1 = -1.0925484305920792,
            kShC2_2 = 0.31539156525252005, kShC2_3 = -1.0925484305920792,
            kShC2_4 = 0.5462742152960396;
const float kShC3_0 = -0.5900435899266435, kShC3_1 = 2.890611442640554,
            kShC3_2 = -0.4570457994644658, kShC3_3 = 0.3731763325901154,
            kShC3_4 = -0.4570457994644658, kShC3_5 = 1.445305721320277,
            kShC3_6 = -0.5900435899266435;

// k is a constant at every call, so the group (binding) is too.
vec3 ShCoeff(uint i, uint K, uint k) {
  const uint g = k / SH_GROUP;
  const uint o = i * ShGroupFloats(K, g) + (k % SH_GROUP) * 3u;
  if (g == 0u) return vec3(sh0[o], sh0[o + 1u], sh0[o + 2u]);
  if (g == 1u) return vec3(sh1[o], sh1[o + 1u], sh1[o + 2u]);
  if (g == 2u) return vec3(sh2[o], sh2[o + 1u], sh2[o + 2u]);
  return vec3(sh3[o], sh3[o + 1u], sh3[o + 2u]);
}

// Accumulates in the same order as the reference loop (v += basis[k] * sh[k], k ascending).
vec3 ShColor(uint i, vec3 dir) {
  const uint K = uint((cam.sh_degree + 1) * (cam.sh_degree + 1));
  const float x = dir.x, y = dir.y, z = dir.z;
  vec3 v = vec3(0.0);
  v += kShC0 * ShCoeff(i, K, 0u);
  if (cam.sh_degree >= 1) {
    v += (-kShC1 * y) * ShCoeff(i, K, 1u);
    v += (kShC1 * z) * ShCoeff(i, K, 2u);
    v += (-kShC1 * x) * ShCoeff(i, K, 3u);
  }
  if (cam.sh_degree >= 2) {
    const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    v += (kShC2_0 * xy) * ShCoeff(i, K, 4u);
    v += (kShC2_1 * yz) * ShCoeff(i, K, 5u);
    v += (kShC2_2 * (2.0 * zz - xx - yy)) * ShCoeff(i, K, 6u);
    v += (kShC2_3 * xz) * ShCoeff(i, K, 7u);
    v += (kShC2_4 * (xx - yy)) * ShCoeff(i, K, 8u);
    if (cam.sh_degree >= 3) {
      v += (kShC3_0 * y * (3.0 * xx - yy)) * ShCoeff(i, K, 9u);
      v += (kShC3_1 * xy * z) * ShCoeff(i, K, 10u);
      v += (kShC3_2 * y * (4.0 * zz - xx - yy)) * ShCoeff(i, K, 11u);
      v += (kShC3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * ShCoeff(i, K, 12u);
      v += (kShC3_4 * x * (4.0 * zz - xx - yy)) * ShCoeff(i, K, 13u);
      v += (kShC3_5 * z * (xx - yy)) * ShCoeff(i, K, 14u);
      v += (kShC3_6 * x * (xx - 3.0 * yy)) * ShCoeff(i, K, 15u);
    }
  }
  return vec3(smax(v.x + 0.5, 0.0), smax(v.y + 0.5, 0.0), smax(v.z + 0.5, 0.0));
}

int ClampTile(float v, int hi) { return int(smin(smax(v, 0.0), float(hi))); }

// Returns false when culled; else fills the splat record and the tile rect.
bool Project(uint i, out vec4 s0, out vec4 s1, out vec4 s2, out ivec4 rect) {
  s0 = vec4(0.0); s1 = vec4(0.0); s2 = vec4(0.0); rect = ivec4(0);
  const vec4 g0 = gauss[3u * i], g1 = gauss[3u * i + 1u], q = gauss[3u * i + 2u];
  const vec3 mean = g0.xyz;
  const float px = cam.R[0] * mean.x + cam.R[1] * mean.y + cam.R[2] * mean.z + cam.t[0];
  const float py = cam.R[3] * mean.x + cam.R[4] * mean.y + cam.R[5] * mean.z + cam.t[1];
  const float pz = cam.R[6] * mean.x + cam.R[7] * mean.y + cam.R[8] * mean.z + cam.t[2];
  if (!(pz > 0.2)) return false;

  const float opacity = 1.0 / (1.0 + exp(-g0.w));
  if (!(opacity * 255.0 > 1.0)) return false;

  // QuatToRotation.
  const float inv = 1.0 / sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
  const float w = q.x * inv, x = q.y * inv, y = q.z * inv, z = q.w * inv;
  float Rq[9];
  Rq[0] = 1.0 - 2.0 * (y * y + z * z); Rq[1] = 2.0 * (x * y - w * z); Rq[2] = 2.0 * (x * z + w * y);
  Rq[3] = 2.0 * (x * y + w * z); Rq[4] = 1.0 - 2.0 * (x * x + z * z); Rq[5] = 2.0 * (y * z - w * x);
  Rq[6] = 2.0 * (x * z - w * y); Rq[7] = 2.0 * (y * z + w * x); Rq[8] = 1.0 - 2.0 * (x * x + y * y);
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
  const float tx = pz * smin(lim_x_pos, smax(-lim_x_neg, px * inv_z));
  const float ty = pz * smin(lim_y_pos, smax(-lim_y_neg, py * inv_z));
  const float j00 = cam.fx * inv_z, j02 = -cam.fx * tx * inv_z * inv_z;
  const float j11 = cam.fy * inv_z, j12 = -cam.fy * ty * inv_z * inv_z;
  const float T0[3] = float[3](j00 * cam.R[0] + j02 * cam.R[6], j00 * cam.R[1] + j02 * cam.R[7],
                               j00 * cam.R[2] + j02 * cam.R[8]);
  const float T1[3] = float[3](j11 * cam.R[3] + j12 * cam.R[6], j11 * cam.R[4] + j12 * cam.R[7],
                               j11 * cam.R[5] + j12 * cam.R[8]);
  // ProjectCovariance: cov = P P^T + 0.3 I with P = T M, and its determinant through Lagrange's
  // identity (no cancellation for needle splats).
  float p0[3], p1[3];
  for (int k = 0; k < 3; ++k) {
    p0[k] = T0[0] * M[k] + T0[1] * M[3 + k] + T0[2] * M[6 + k];
    p1[k] = T1[0] * M[k] + T1[1] * M[3 + k] + T1[2] * M[6 + k];
  }
  const float n0 = p0[0] * p0[0] + p0[1] * p0[1] + p0[2] * p0[2];
  const float n1 = p1[0] * p1[0] + p1[1] * p1[1] + p1[2] * p1[2];
  const float x0 = p0[1] * p1[2] - p0[2] * p1[1];
  const float x1 = p0[2] * p1[0] - p0[0] * p1[2];
  const float x2 = p0[0] * p1[1] - p0[1] * p1[0];
  const float cov_xx = n0 + 0.3;
  const float cov_xy = p0[0] * p1[0] + p0[1] * p1[1] + p0[2] * p1[2];
  const float cov_yy = n1 + 0.3;
  const float det = (x0 * x0 + x1 * x1 + x2 * x2) + 0.3 * (n0 + n1) + 0.3 * 0.3;
  if (!(det > 0.0) || !finite(det)) return false;
  const float inv_det = 1.0 / det;

  const float sx = cam.fx * px * inv_z + cam.cx;
  const float sy = cam.fy * py * inv_z + cam.cy;
  if (!finite(sx) || !finite(sy)) return false;

  const float mid = 0.5 * (cov_xx + cov_yy);
  const float lambda_max = mid + sqrt(smax(0.1, mid * mid - det));
  const float radius = ceil(3.0 * sqrt(lambda_max));
  const float d2 = 2.0 * log(opacity * 255.0);
  const float half_w = smin(radius, sqrt(d2 * cov_xx));
  const float half_h = smin(radius, sqrt(d2 * cov_yy));
  const float ts = float(TILE_SIZE);
  rect.x = ClampTile(floor((sx - half_w) / ts), cam.tiles_x);
  rect.z = ClampTile(floor((sx + half_w) / ts) + 1.0, cam.tiles_x);
  rect.y = ClampTile(floor((sy - half_h) / ts), cam.tiles_y);
  rect.w = ClampTile(floor((sy + half_h) / ts) + 1.0, cam.tiles_y);
  if (rect.z <= rect.x || rect.w <= rect.y) return false;

  const vec3 dir = mean - vec3(cam.c[0], cam.c[1], cam.c[2]);
  const float inv_len = 1.0 / sqrt(dir.x * dir.x + dir.y * dir.y + dir.z * dir.z);
  const vec3 rgb = ShColor(i, vec3(dir.x * inv_len, dir.y * inv_len, dir.z * inv_len));

  s0 = vec4(sx, sy, cov_yy * inv_det, -cov_xy * inv_det);
  s1 = vec4(cov_xx * inv_det, opacity, rgb.r, rgb.g);
  s2 = vec4(rgb.b, pz, half_h, 0.0);
  return true;
}

void main() {
  const uint i = linear_thread_id();
  if (i >= cam.n) return;
  vec4 s0, s1, s2;
  ivec4 rect;
  const bool visible = Project(i, s0, s1, s2, rect);
  if (visible) {
    splats[3u * i] = s0;
    splats[3u * i + 1u] = s1;
    splats[3u * i + 2u] = s2;
    rects[i] = uvec2(uint(rect.x) | (uint(rect.y) << 16), uint(rect.z) | (uint(rect.w) << 16));
  }
  flags[i] = visible ? 1u : 0u;
  touched[i] = visible ? uint((rect.z - rect.x) * (rect.w - rect.y)) : 0u;
}
