// LiDAR stage a: one thread per Gaussian. Mirrors the scalar reference projection of
// render/lidar/lidar_renderer.cc (ProjectScalar + FillSplat) operation for operation in float, with
// the beam map of the vectorised kernel (float radians, the segment found by counting the table
// entries above the elevation: exactly lidar_model.cc's search) and LidarAtan2 (lidar_common.glsl).
// Writes the splat record by Gaussian id and, per entry (2i: the splat, 2i + 1: its seam copy),
// the tile rect, a drawn flag and the tile count.
#version 460
#extension GL_GOOGLE_include_directive : require
#include "lidar_common.glsl"

// Rolling sweep (one pose per column): a pipeline of its own, so that the static sweep's
// projection loads its one pose with uniform loads and skips the first projection.
layout(constant_id = 0) const uint kRolling = 0u;

layout(local_size_x = WG_SIZE) in;

layout(std430, binding = 0) readonly buffer Gaussians { vec4 gauss[]; };
layout(std430, binding = 1) readonly buffer Table { float table[]; };
layout(std430, binding = 2) readonly buffer Reflectance { float refl[]; };
layout(std430, binding = 3) writeonly buffer Splats { vec4 splats[]; };
layout(std430, binding = 4) writeonly buffer Rects { uvec2 rects[]; };
layout(std430, binding = 5) writeonly buffer Flags { uint flags[]; };
layout(std430, binding = 6) writeonly buffer Touched { uint touched[]; };

layout(push_constant, std430) uniform Params {
  uint n;
  int columns, beams, tiles_x, tiles_y;
  float near_m, far_m, cols_per_rad;
  uint pose_offset;  // first float of the pose table
  uint rolling;      // unused: kRolling
  uint has_refl;     // 0: reflectance 0.5 for every Gaussian
} pc;

float smin(float a, float b) { return (b < a) ? b : a; }
float smax(float a, float b) { return (a < b) ? b : a; }
bool finite(float v) { return !isnan(v) && !isinf(v); }

const float kPi = 3.14159265358979324;

vec3 Transform(uint pose, vec3 m, out float R[9]) {
  const uint o = pc.pose_offset + pose * POSE_STRIDE;
  for (int k = 0; k < 9; ++k) R[k] = table[o + uint(k)];
  return vec3(R[0] * m.x + R[1] * m.y + R[2] * m.z + table[o + 9u],
              R[3] * m.x + R[4] * m.y + R[5] * m.z + table[o + 10u],
              R[6] * m.x + R[7] * m.y + R[8] * m.z + table[o + 11u]);
}

// Continuous column coordinate of a sensor-frame direction, wrapped to [-0.5, columns - 0.5).
float ColumnOf(float px, float py) {
  const float W = float(pc.columns);
  float u = (kPi - LidarAtan2(py, px)) * pc.cols_per_rad - 0.5;
  u = u >= W - 0.5 ? u - W : u;
  return u < -0.5 ? u + W : u;
}

int ClampTile(float v, int hi) { return int(smin(smax(v, 0.0), float(hi))); }

// FillSplat's rect_of: tile rect of a splat at column x (half extents half_w, half_h); empty as
// (0, 0, 0, 0).
ivec4 RectOf(float x, float y, float half_w, float half_h) {
  const float ts = float(TILE_SIZE);
  ivec4 r;
  r.x = ClampTile(floor((x - half_w) / ts), pc.tiles_x);
  r.z = ClampTile(floor((x + half_w) / ts) + 1.0, pc.tiles_x);
  r.y = ClampTile(floor((y - half_h) / ts), pc.tiles_y);
  r.w = ClampTile(floor((y + half_h) / ts) + 1.0, pc.tiles_y);
  return (r.z <= r.x || r.w <= r.y) ? ivec4(0) : r;
}

uint Count(ivec4 r) { return uint((r.z - r.x) * (r.w - r.y)); }
uvec2 Pack(ivec4 r) {
  return uvec2(uint(r.x) | (uint(r.y) << 16), uint(r.z) | (uint(r.w) << 16));
}

void main() {
  const uint i = linear_thread_id();
  if (i >= pc.n) return;
  uint drawn = 0u;  // bit 0: the splat, bit 1: its seam copy
  ivec4 rect = ivec4(0), rect2 = ivec4(0);
  const vec4 g0 = gauss[3u * i], g1 = gauss[3u * i + 1u], q = gauss[3u * i + 2u];
  const vec3 mean = g0.xyz;

  // Rolling sweep: the pose of the column the Gaussian falls in under the middle column's pose.
  float R[9];
  uint pose = 0u;  // the pose table entry: kept in the splat record for the backward
  if (kRolling != 0u) {
    const vec3 p0 = Transform(uint(pc.columns / 2), mean, R);
    const float u0 = ColumnOf(p0.x, p0.y);
    const float c = smin(smax(floor(u0 + 0.5), 0.0), float(pc.columns - 1));
    pose = finite(u0) ? uint(c) : uint(pc.columns / 2);
  }
  const vec3 p = Transform(pose, mean, R);
  const float px = p.x, py = p.y, pz = p.z;
  const float rho2 = px * px + py * py;
  const float r2 = rho2 + pz * pz;
  const float range = sqrt(r2);
  const float rho = sqrt(rho2);
  const float opacity = 1.0 / (1.0 + exp(-g0.w));
  // Culls as the reference: range window (also NaN), straight up/down, transparent.
  bool ok = range > pc.near_m && range < pc.far_m && rho > 1e-3 * range && opacity * 255.0 > 1.0;

  vec4 s0 = vec4(0.0), s1 = vec4(0.0), s2 = vec4(0.0);
  if (ok) {
    // M = R diag(s) (projection_math.h: QuatToRotation, ScaledRotation).
    const float inv = 1.0 / sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    const float w = q.x * inv, x = q.y * inv, y = q.z * inv, z = q.w * inv;
    float Rq[9];
    Rq[0] = 1.0 - 2.0 * (y * y + z * z); Rq[1] = 2.0 * (x * y - w * z); Rq[2] = 2.0 * (x * z + w * y);
    Rq[3] = 2.0 * (x * y + w * z); Rq[4] = 1.0 - 2.0 * (x * x + z * z); Rq[5] = 2.0 * (y * z - w * x);
    Rq[6] = 2.0 * (x * z - w * y); Rq[7] = 2.0 * (y * z + w * x); Rq[8] = 1.0 - 2.0 * (x * x + y * y);
    const float s[3] = float[3](exp(clamp(g1.x, -30.0, 30.0)), exp(clamp(g1.y, -30.0, 30.0)),
                                exp(clamp(g1.z, -30.0, 30.0)));
    float M[9];
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) M[r * 3 + k] = Rq[r * 3 + k] * s[k];

    // Spherical projection and its Jacobian at the sensor-frame mean:
    //   u = (pi - atan2(y, x)) W / 2pi - 0.5:  du/dp = W/2pi (y, -x, 0) / rho^2
    //   v = beam(atan2(z, rho)):              dv/dp = beam'(el) (-x z / rho, -y z / rho, rho) / r^2
    const float el = LidarAtan2(pz, rho);
    // Segment k = #{m in 1 .. beams-2 : elev[m] > el}: the table decreases, so a binary search
    // for the last m with elev[m] > el (uniform steps; a 62-step count was 2x slower on lavapipe).
    const int L = pc.beams - 2;
    int k = 0;
    for (int step = 1 << findMSB(max(L, 1)); step > 0; step >>= 1) {
      const int m = min(k + step, max(L, 1));
      k += (k + step <= L && table[m] > el) ? step : 0;
    }
    const float dbeam = table[pc.beams + k];
    const float v = float(k) + (el - table[k]) * dbeam;
    const float u = ColumnOf(px, py);
    const float ku = pc.cols_per_rad / rho2;
    const float kv = dbeam / r2;
    const float J0[3] = float[3](ku * py, -ku * px, 0.0);
    const float J1[3] = float[3](-kv * px * pz / rho, -kv * py * pz / rho, kv * rho);
    float T0[3], T1[3];
    for (int c = 0; c < 3; ++c) {
      T0[c] = J0[0] * R[c] + J0[1] * R[3 + c] + J0[2] * R[6 + c];
      T1[c] = J1[0] * R[c] + J1[1] * R[3 + c] + J1[2] * R[6 + c];
    }
    // ProjectCovariance: cov = P P^T + 0.3 I with P = T M, det by Lagrange's identity.
    float p0[3], p1[3];
    for (int c = 0; c < 3; ++c) {
      p0[c] = T0[0] * M[c] + T0[1] * M[3 + c] + T0[2] * M[6 + c];
      p1[c] = T1[0] * M[c] + T1[1] * M[3 + c] + T1[2] * M[6 + c];
    }
    const float n0 = p0[0] * p0[0] + p0[1] * p0[1] + p0[2] * p0[2];
    const float n1 = p1[0] * p1[0] + p1[1] * p1[1] + p1[2] * p1[2];
    const float q0 = p0[1] * p1[2] - p0[2] * p1[1];
    const float q1 = p0[2] * p1[0] - p0[0] * p1[2];
    const float q2 = p0[0] * p1[1] - p0[1] * p1[0];
    const float cxx = n0 + 0.3;
    const float cxy = p0[0] * p1[0] + p0[1] * p1[1] + p0[2] * p1[2];
    const float cyy = n1 + 0.3;
    const float det = (q0 * q0 + q1 * q1 + q2 * q2) + 0.3 * (n0 + n1) + 0.3 * 0.3;
    ok = det > 0.0 && finite(det);
    const float inv_det = 1.0 / det;

    const float mid = 0.5 * (cxx + cyy);
    const float lambda_max = mid + sqrt(smax(0.1, mid * mid - det));
    const float radius = ceil(3.0 * sqrt(lambda_max));
    const float d2 = 2.0 * log(opacity * 255.0);
    const float op_w = sqrt(d2 * cxx), op_h = sqrt(d2 * cyy);
    const float half_w = smin(radius, op_w), half_h = smin(radius, op_h);
    ok = ok && finite(u) && finite(v) && finite(half_w) && finite(half_h);
    // Rows beyond the image: nothing to draw.
    ok = ok && !(v + half_h < -0.5) && !(v - half_h > float(pc.beams) - 0.5);
    const float W = float(pc.columns);
    float x2 = 0.0;
    if (ok) {
      rect = RectOf(u, v, half_w, half_h);
      drawn = Count(rect) > 0u ? 1u : 0u;
      // The seam behind the sensor: a splat reaching past either end of the columns is drawn
      // again one turn away (not when it spans more than half a turn: it would be drawn twice).
      const bool wrap_lo = u - half_w < -0.5, wrap_hi = u + half_w > W - 0.5;
      if (half_w < 0.5 * W && (wrap_lo || wrap_hi)) {
        x2 = wrap_hi ? u - W : u + W;
        rect2 = RectOf(x2, v, half_w, half_h);
        drawn |= Count(rect2) > 0u ? 2u : 0u;
      }
    }
    const float reflectance = pc.has_refl != 0u ? clamp(refl[i], 0.0, 1.0) : 0.5;
    s0 = vec4(u, v, op_w, op_h);
    s1 = vec4(cyy * inv_det, -cxy * inv_det, cxx * inv_det, opacity);
    s2 = vec4(reflectance, range, x2, float(pose));
  }
  if (drawn != 0u) {
    splats[3u * i] = s0;
    splats[3u * i + 1u] = s1;
    splats[3u * i + 2u] = s2;
  }
  const bool main_drawn = (drawn & 1u) != 0u, copy_drawn = (drawn & 2u) != 0u;
  rects[2u * i] = Pack(rect);
  rects[2u * i + 1u] = Pack(rect2);
  flags[2u * i] = main_drawn ? 1u : 0u;
  flags[2u * i + 1u] = copy_drawn ? 1u : 0u;
  touched[2u * i] = main_drawn ? Count(rect) : 0u;
  touched[2u * i + 1u] = copy_drawn ? Count(rect2) : 0u;
}
