// Stages the float renderer and the double reference share: the SoA copy of a store, and the sort
// by range with the binning into per-tile front-to-back lists.
#include <algorithm>

#include "render/common/thread_pool.h"
#include "render/cpu/binning.h"
#include "render/lidar/lidar_kernels.h"
#include "render/lidar/lidar_reference.h"

namespace streetsim::lidar {

void CopyToSoa(ThreadPool& pool, const GaussianStore& store, LidarSoa* soa) {
  LidarSoa& s = *soa;
  const size_t n = store.size();
  s.n = n;
  for (auto* v : {&s.mx, &s.my, &s.mz, &s.ls0, &s.ls1, &s.ls2, &s.qw, &s.qx, &s.qy, &s.qz, &s.opacity_logit}) {
    v->resize(n);
  }
  pool.ParallelFor(static_cast<int64_t>(n), 16384, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      s.mx[i] = store.means[i * 3];
      s.my[i] = store.means[i * 3 + 1];
      s.mz[i] = store.means[i * 3 + 2];
      s.ls0[i] = store.log_scales[i * 3];
      s.ls1[i] = store.log_scales[i * 3 + 1];
      s.ls2[i] = store.log_scales[i * 3 + 2];
      s.qw[i] = store.rotations[i * 4];
      s.qx[i] = store.rotations[i * 4 + 1];
      s.qy[i] = store.rotations[i * 4 + 2];
      s.qz[i] = store.rotations[i * 4 + 3];
      s.opacity_logit[i] = store.opacity_logits[i];
    }
  });
}

void SortAndBin(ThreadPool& pool, std::vector<uint32_t>* keys, std::vector<uint32_t>* ids, const Rect* rects,
                int tiles_x, int tiles_y, BinScratch* scratch, std::vector<uint32_t>* tile_offsets,
                std::vector<uint32_t>* tile_ids) {
  const int num_tiles = tiles_x * tiles_y;
  const int64_t V = static_cast<int64_t>(ids->size());
  // The camera binning's stable radix sort (single-threaded: a pooled version was no faster on 2
  // cores, measured back to back).
  cpu::RadixSortPairs(keys, ids, &scratch->scratch_keys, &scratch->scratch_ids);
  // Binning: per-chunk counts, a scan in (tile, chunk) order, per-chunk scatters; contiguous chunks
  // of the range order keep every tile's list in range order.
  std::vector<Rect>& sorted_rects = scratch->sorted_rects;
  sorted_rects.resize(V);
  const int64_t chunks = std::min<int64_t>(pool.num_threads(), std::max<int64_t>(1, V / 4096));
  const int64_t len = (V + chunks - 1) / chunks;
  std::vector<uint32_t>& bin_counts = scratch->bin_counts;
  bin_counts.assign(static_cast<size_t>(chunks) * num_tiles, 0);
  const uint32_t* id = ids->data();
  pool.ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
    for (int64_t c = c0; c < c1; ++c) {
      uint32_t* cnt = &bin_counts[c * num_tiles];
      // The gather first, in a loop of its own (independent misses overlap), then the counts.
      for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) sorted_rects[j] = rects[id[j]];
      for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) {
        const Rect r = sorted_rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
          for (int tx = r.x0; tx < r.x1; ++tx) ++cnt[ty * tiles_x + tx];
      }
    }
  });
  tile_offsets->resize(num_tiles + 1);
  uint32_t sum = 0;
  for (int t = 0; t < num_tiles; ++t) {
    (*tile_offsets)[t] = sum;
    for (int64_t c = 0; c < chunks; ++c) {
      uint32_t& v = bin_counts[c * num_tiles + t];
      const uint32_t cnt = v;
      v = sum;
      sum += cnt;
    }
  }
  (*tile_offsets)[num_tiles] = sum;
  tile_ids->resize(sum);
  pool.ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
    for (int64_t c = c0; c < c1; ++c) {
      uint32_t* cursor = &bin_counts[c * num_tiles];
      for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) {
        const Rect r = sorted_rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
          for (int tx = r.x0; tx < r.x1; ++tx) (*tile_ids)[cursor[ty * tiles_x + tx]++] = id[j];
      }
    }
  });
}

}  // namespace streetsim::lidar
