#include "render/cpu/binning.h"

#include <algorithm>
#include <bit>
#include <cstring>

namespace streetsim::cpu {

void RadixSortPairs(std::vector<uint32_t>* keys, std::vector<uint32_t>* values,
                    std::vector<uint32_t>* scratch_keys, std::vector<uint32_t>* scratch_values) {
  constexpr int kBits = 11;
  constexpr uint32_t kBins = 1u << kBits;
  const size_t n = keys->size();
  scratch_keys->resize(n);
  scratch_values->resize(n);
  uint32_t* src_k = keys->data();
  uint32_t* src_v = values->data();
  uint32_t* dst_k = scratch_keys->data();
  uint32_t* dst_v = scratch_values->data();

  // One read to build every digit's histogram; passes whose digit is constant are skipped
  // (depth keys share their top exponent bits, so typically only 2 of 3 passes run).
  std::vector<uint32_t> hist(3 * kBins, 0);
  for (size_t i = 0; i < n; ++i) {
    const uint32_t k = src_k[i];
    ++hist[k & (kBins - 1)];
    ++hist[kBins + ((k >> kBits) & (kBins - 1))];
    ++hist[2 * kBins + (k >> (2 * kBits))];
  }
  bool swapped = false;
  for (int pass = 0; pass < 3; ++pass) {
    uint32_t* h = &hist[pass * kBins];
    if (std::any_of(h, h + kBins, [n](uint32_t c) { return c == n; })) continue;
    uint32_t sum = 0;
    for (uint32_t b = 0; b < kBins; ++b) {
      const uint32_t c = h[b];
      h[b] = sum;
      sum += c;
    }
    const int shift = pass * kBits;
    for (size_t i = 0; i < n; ++i) {
      const uint32_t k = src_k[i];
      const uint32_t pos = h[(k >> shift) & (kBins - 1)]++;
      dst_k[pos] = k;
      dst_v[pos] = src_v[i];
    }
    std::swap(src_k, dst_k);
    std::swap(src_v, dst_v);
    swapped = !swapped;
  }
  if (swapped) {
    keys->swap(*scratch_keys);
    values->swap(*scratch_values);
  }
}

namespace {
// Monotonic 32-bit key of a positive depth. Depths are > the near plane (0.2 m) so the float bits
// order like the values; double depths are narrowed first (ties then break by id, as on vulkan).
template <typename Real>
uint32_t DepthKey(Real depth) {
  return std::bit_cast<uint32_t>(static_cast<float>(depth));
}
}  // namespace

template <typename Real>
void SortByDepth(Frame<Real>* frame) {
  const size_t n = frame->visible_ids.size();
  std::vector<uint32_t>& keys = frame->sort_keys;
  keys.resize(n);
  for (size_t i = 0; i < n; ++i) keys[i] = DepthKey(frame->splats[frame->visible_ids[i]].depth);
  frame->depth_sorted_ids = frame->visible_ids;
  RadixSortPairs(&keys, &frame->depth_sorted_ids, &frame->sort_scratch_keys,
                 &frame->sort_scratch_values);
  // Binning reads every rect twice (count, scatter); one gather here makes both passes stream.
  frame->depth_sorted_rects.resize(n);
  for (size_t j = 0; j < n; ++j) frame->depth_sorted_rects[j] = frame->rects[frame->depth_sorted_ids[j]];
}

template <typename Real>
void BinTiles(ThreadPool& pool, Frame<Real>* frame) {
  const int num_tiles = frame->tiles_x * frame->tiles_y;
  const std::vector<uint32_t>& order = frame->depth_sorted_ids;
  const std::vector<projection::TileRect>& rects = frame->depth_sorted_rects;
  const int64_t n = static_cast<int64_t>(order.size());
  const int threads = pool.num_threads();
  // Contiguous chunks of the depth order per worker keep each tile's entries in depth order after
  // the scatter: chunk c's entries land after chunks 0..c-1's within every tile.
  const int64_t chunks = std::min<int64_t>(threads, std::max<int64_t>(1, n / 4096));
  const int64_t chunk_len = (n + chunks - 1) / std::max<int64_t>(1, chunks);
  std::vector<uint32_t> counts(static_cast<size_t>(chunks) * num_tiles, 0);

  pool.ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
    for (int64_t c = c0; c < c1; ++c) {
      uint32_t* cnt = &counts[c * num_tiles];
      for (int64_t j = c * chunk_len; j < std::min(n, (c + 1) * chunk_len); ++j) {
        const projection::TileRect& r = rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
          for (int tx = r.x0; tx < r.x1; ++tx) ++cnt[ty * frame->tiles_x + tx];
      }
    }
  });

  // Exclusive scan in (tile, chunk) order; counts become each chunk's write cursor per tile.
  frame->tile_offsets.resize(num_tiles + 1);
  uint32_t sum = 0;
  for (int t = 0; t < num_tiles; ++t) {
    frame->tile_offsets[t] = sum;
    for (int64_t c = 0; c < chunks; ++c) {
      const uint32_t v = counts[c * num_tiles + t];
      counts[c * num_tiles + t] = sum;
      sum += v;
    }
  }
  frame->tile_offsets[num_tiles] = sum;
  frame->tile_ids.resize(sum);

  pool.ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
    for (int64_t c = c0; c < c1; ++c) {
      uint32_t* cursor = &counts[c * num_tiles];
      for (int64_t j = c * chunk_len; j < std::min(n, (c + 1) * chunk_len); ++j) {
        const uint32_t id = order[j];
        const projection::TileRect& r = rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
          for (int tx = r.x0; tx < r.x1; ++tx) frame->tile_ids[cursor[ty * frame->tiles_x + tx]++] = id;
      }
    }
  });
}

template void SortByDepth<float>(Frame<float>*);
template void SortByDepth<double>(Frame<double>*);
template void BinTiles<float>(ThreadPool&, Frame<float>*);
template void BinTiles<double>(ThreadPool&, Frame<double>*);

}  // namespace streetsim::cpu
