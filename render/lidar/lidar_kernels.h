// Internal to render/lidar: the data the LiDAR renderer's stages share, and the vectorised
// kernels (lidar_simd.inc, compiled once per ISA: lidar_simd_avx2.cc, lidar_simd_avx512.cc,
// picked at run time through render/cpu/simd_dispatch.h).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

namespace streetsim {
class ThreadPool;
}

namespace streetsim::lidar {

constexpr int kTile = 16;
constexpr float kLowPassPx = 0.3f;
constexpr float kMinAlpha = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.99f;
constexpr float kMinTransmittance = 1e-4f;
constexpr float kNearM = 0.2f;

// What the blender reads per splat (40 bytes in float; the blend streams copies of these in tile
// order). Real = double only in the gradient-check reference (lidar_reference.h).
template <typename Real>
struct LidarSplatT {
  Real x, y;      // column, beam coordinates of the mean
  Real a, b, c;   // conic: power = -0.5 (a dx^2 + c dy^2) - b dx dy
  Real opacity;
  Real range;     // |mean| in the sensor frame of the Gaussian's pose column, metres
  Real refl;
  Real op_w, op_h;  // opacity box half extents (px): outside it opacity * G < 1/255
  Real det_conic;   // a c - b^2 = 1 / det(cov), from the covariance (from the conic it cancels for needles)
};
using LidarSplat = LidarSplatT<float>;

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

// Rolling sweep: column c's sensor pose as lidar_from_world, R row-major then t (12 values per
// column, lidar_sweep.h). Every Gaussian is projected with one column's entry (docs/lidar.md).
constexpr int kPoseStride = 12;

// Per-sweep constants of the projection.
struct LidarProjectParams {
  float R[9], t[3];  // lidar_from_world of the middle column (the static pose when !rolling)
  // [columns * kPoseStride]; with rolling set, each Gaussian's column coordinate u0 under the
  // middle column's pose picks entry clamp(floor(u0 + 0.5), 0, columns - 1), with which it is
  // projected (one fixed-point step). Without rolling every column has the pose R, t.
  const float* pose_table = nullptr;
  bool rolling = false;
  // [n], required: the pose column of every drawn Gaussian (what the backward treats as constant).
  uint32_t* gauss_col = nullptr;
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
// keys[k]: the float bits of splats[k].range (the sort key); gauss[k]: its Gaussian's index.
template <typename Real>
struct LidarProjectOutT {
  LidarSplatT<Real>* splats;
  Rect* rects;
  uint32_t* keys;
  uint32_t* gauss;
  uint32_t count;
};
using LidarProjectOut = LidarProjectOutT<float>;

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

// Sorts the splats by range (keys: float bits, ties by position in ids) and bins them into the
// tiles' front-to-back lists (tile_offsets [tiles + 1], tile_ids). rects[id] is splat id's tile
// rectangle. Shared by the float renderer and the double reference; thread-count independent.
struct BinScratch {
  std::vector<uint32_t> scratch_keys, scratch_ids, bin_counts;
  std::vector<Rect> sorted_rects;
};
void SortAndBin(ThreadPool& pool, std::vector<uint32_t>* keys, std::vector<uint32_t>* ids,
                const Rect* rects, int tiles_x, int tiles_y, BinScratch* scratch,
                std::vector<uint32_t>* tile_offsets, std::vector<uint32_t>* tile_ids);

// The blend backward's inputs (lidar_backward_simd.inc): the forward's splats and tile lists, each
// splat's Gaussian, and the upstream gradients per ray ([beams * columns] or null).
constexpr int kLidarBackwardTerms = 8;  // lidar_backward.h: LidarSplatGrad
struct LidarBlendBackwardArgs {
  const LidarSplat* splats;
  const uint32_t* splat_gauss;
  const uint32_t* tile_offsets;
  const uint32_t* tile_ids;
  int beams, columns, tiles_x;
  const float* d_range_sum;
  const float* d_alpha;
  const float* d_intensity_sum;
};

#define STREETSIM_LIDAR_KERNELS(NS)                                                                \
  namespace NS {                                                                                   \
  void ProjectRange(const LidarSoa& s, const LidarProjectParams& p, int64_t begin, int64_t end,   \
                    LidarProjectOut* out);                                                          \
  void BlendTiles(const LidarBlendArgs& args, int64_t tile_begin, int64_t tile_end);               \
  /* Tiles [tile_begin, tile_end): adds kLidarBackwardTerms per (splat, tile) into              \
     acc[gauss * 8 + k], or with per_instance into per_instance[list position * 8 + k]. */        \
  void BlendBackwardTiles(const LidarBlendBackwardArgs& args, int64_t tile_begin, int64_t tile_end, \
                          float* acc, float* per_instance);                                         \
  }
STREETSIM_LIDAR_KERNELS(simd_avx2)
STREETSIM_LIDAR_KERNELS(simd_avx512)
#undef STREETSIM_LIDAR_KERNELS

}  // namespace streetsim::lidar
