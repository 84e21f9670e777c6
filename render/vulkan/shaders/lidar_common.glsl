// Shared layout of the vulkan LiDAR kernels (lidar_*.comp; host side: render/vulkan/lidar_stages_vk.h,
// rules: docs/lidar.md). The sort, scans, emit and tile ranges are the camera path's kernels
// (common.glsl), run over "entries": entry 2i is Gaussian i's splat, entry 2i + 1 its copy one turn
// away when it crosses the seam behind the sensor.
#ifndef STREETSIM_LIDAR_COMMON_GLSL_
#define STREETSIM_LIDAR_COMMON_GLSL_

#include "common.glsl"

// Projected LiDAR splat, 3 vec4 per Gaussian (lidar_project.comp, by Gaussian id) and per drawn
// entry in range order (lidar_gather.comp, the copy's x already substituted):
//   [0] = (x column, y beam, op_w, op_h), [1] = (conic a, b, c, opacity),
//   [2] = (reflectance, range, x of the seam copy, pose table entry it was projected with: exact
//   in float; the backward reprojects with it, lidar_project_backward.comp).
// op_w / op_h: the opacity box's half extents (outside it opacity * G < 1/255): the blend's reach
// test reads [0] only.

// The sweep table (one float buffer, host-written per sweep): beam elevations in radians
// [0, beams), each segment's slope in beams per radian [beams, 2 beams - 1), then from
// pose_offset on, 12 floats per pose (lidar_from_world: R row-major, then t): one pose for a
// static sweep, one per column for a rolling one.
#define POSE_STRIDE 12u

// atan2 without branches: Cephes atanf's reduction to |z| <= tan(pi/8) and its polynomial, as
// render/lidar/lidar_simd.inc (~1e-7 relative). GLSL's atan(y, x) has no precision guarantee
// worth the name (4096 ulp in the Vulkan spec), and the column coordinate needs ~1e-4 px.
float LidarAtan2(float y, float x) {
  const float ax = abs(x), ay = abs(y);
  const float hi = max(ax, ay), lo = min(ax, ay);
  const float a = lo / max(hi, 1e-30);
  const bool big = a > 0.41421356237309503;
  const float z = big ? (a - 1.0) / (a + 1.0) : a;
  const float z2 = z * z;
  float r = (((8.05374449538e-2 * z2 - 1.38776856032e-1) * z2 + 1.99777106478e-1) * z2 -
             3.33329491539e-1) * z2 * z + z;
  r += big ? 0.78539816339744831 : 0.0;
  r = ay > ax ? 1.57079632679489662 - r : r;
  r = x < 0.0 ? 3.14159265358979324 - r : r;
  return y < 0.0 ? -r : r;
}

#endif  // STREETSIM_LIDAR_COMMON_GLSL_
