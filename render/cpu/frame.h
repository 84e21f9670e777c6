// Per-frame working arrays of the cpu backend, kept by the engine and reused across frames so a
// steady stream of renders allocates nothing.
#pragma once

#include <cstdint>
#include <vector>

#include "render/common/projection_math.h"

namespace streetsim::cpu {

// What the blender reads per splat: the projected record plus what lets it skip pixel rows a
// splat cannot reach (all derived from the opacity bound o * G >= 1/255, so skipping is exact).
// 16 scalars: one 64-byte cache line per float splat.
template <typename Real>
struct alignas(sizeof(Real) * 16) BlendSplat {
  Real x, y;
  Real a, b, c;  // conic
  Real opacity;
  Real r, g, bl;
  Real depth;
  Real band;       // half height (px) of the rows the splat reaches
  Real reach2;     // a * d2 with d2 = 2 ln(255 o): row v reaches x where
  Real det_conic;  // |x - (x0 + b/a dy)| <= sqrt(reach2 - det_conic dy^2) / a, dy = y - v
  Real b_over_a;
  Real inv_a;
  Real pad;
};

template <typename Real>
struct Frame {
  int width = 0, height = 0, tiles_x = 0, tiles_y = 0;

  // Indexed by Gaussian id (size N); valid where visible.
  std::vector<BlendSplat<Real>> splats;
  std::vector<projection::TileRect> rects;
  std::vector<uint8_t> visible;

  // Visible ids in index order, then sorted front to back by (depth, id).
  std::vector<uint32_t> visible_ids;
  std::vector<uint32_t> depth_sorted_ids;
  std::vector<projection::TileRect> depth_sorted_rects;  // rects[depth_sorted_ids[j]], gathered once
  std::vector<uint32_t> sort_keys, sort_scratch_keys, sort_scratch_values;  // radix sort scratch

  // Tile lists: tile t holds tile_ids[tile_offsets[t] .. tile_offsets[t+1]), front to back.
  std::vector<uint32_t> tile_offsets;  // num_tiles + 1
  std::vector<uint32_t> tile_ids;

  // Per pixel, kept for the backward pass: final transmittance and how many list entries were
  // processed up to and including the last contributor.
  std::vector<Real> final_T;
  std::vector<uint32_t> n_contrib;
};

}  // namespace streetsim::cpu
