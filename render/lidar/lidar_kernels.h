// Internal to render/lidar: the data the LiDAR renderer's stages share, and the vectorised
// kernels (lidar_simd.inc, compiled once per ISA: lidar_simd_avx2.cc, lidar_simd_avx512.cc,
// picked at run time through render/cpu/simd_dispatch.h).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace streetsim::lidar {

constexpr int kTile = 16;
constexpr float kLowPassPx = 0.3f;
constexpr float kMinAlpha = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.99f;
constexpr float kMinTransmittance = 1e-4f;
constexpr float kNearM = 0.2f;

// What the blender reads per splat (40 bytes; the blend streams copies of these in tile order).
struct LidarSplat {
  float x, y;      // column, beam coordinates of the mean
  float a, b, c;   // conic: power = -0.5 (a dx^2 + c dy^2) - b dx dy
  float opacity;
  float range;     // |mean| in the sensor frame, metres
  float refl;
  float op_w, op_h;  // opacity box half extents (px): outside it opacity * G < 1/255
};

struct Rect {
  int x0, y0, x1, y1;  // tiles, [x0, x1) x [y0, y1)
  int count() const { return (x1 - x0) * (y1 - y0); }
};

// The uploaded scene: one array per scalar parameter (validated finite at upload).
struct LidarSoa {
  size_t n = 0;
  std::vector<float> mx, my, mz;
  std::vector<float> ls0, ls1, ls2;
  std::vector<float> qw, qx, qy, qz;
  std::vector<float> opacity_logit;
};

// Per-sweep constants of the projection.
struct LidarProjectParams {
  float R[9], t[3];  // lidar_from_world, row-major
  float near_m, far_m;
  int columns, beams, tiles_x, tiles_y;
  float cols_per_rad;
  // Beam table in radians (strictly decreasing) and each segment's slope (beams per radian,
  // negative): segment k spans [elev[k+1], elev[k]]; the end segments extrapolate.
  const float* elev = nullptr;
  const float* slope = nullptr;
  const float* reflectance = nullptr;  // [n] or null (0.5)
};

// Where the projection of one block of Gaussians writes its visible splats: densely, in Gaussian
// order (a splat, then its copy one turn away when it crosses the seam), count of them so far.
// keys[k]: the float bits of splats[k].range (the sort key).
struct LidarProjectOut {
  LidarSplat* splats;
  Rect* rects;
  uint32_t* keys;
  uint32_t count;
};

// A tile's blend output goes to these [beams * columns] planes.
struct LidarBlendArgs {
  // Tile t's splats, front to back: splats[tile_ids[j]] for j in [tile_offsets[t], tile_offsets[t + 1]).
  const LidarSplat* splats;
  const uint32_t* tile_offsets;
  const uint32_t* tile_ids;
  int beams, columns, tiles_x;
  float* T;      // final transmittance
  float* range_sum;
  float* intensity_sum;
};

// Finishes a projected splat sp whose tile box has half extents (half_w, half_h): the image-row
// cull, tile rects, and the copy one turn away when it crosses the seam; appends to out. The
// scalar projection's (lidar_renderer.cc); lidar_simd.inc computes the same vectorised.
void FillSplat(const LidarProjectParams& p, const LidarSplat& sp, float half_w, float half_h,
               LidarProjectOut* out);

#define STREETSIM_LIDAR_KERNELS(NS)                                                                \
  namespace NS {                                                                                   \
  void ProjectRange(const LidarSoa& s, const LidarProjectParams& p, int64_t begin, int64_t end,   \
                    LidarProjectOut* out);                                                          \
  void BlendTiles(const LidarBlendArgs& args, int64_t tile_begin, int64_t tile_end);               \
  }
STREETSIM_LIDAR_KERNELS(simd_avx2)
STREETSIM_LIDAR_KERNELS(simd_avx512)
#undef STREETSIM_LIDAR_KERNELS

}  // namespace streetsim::lidar
