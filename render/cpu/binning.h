// cpu sort and tile binning: visible splats -> per-tile front-to-back lists.
//
// Two stable passes instead of one 64-bit (tile, depth) key sort: a 32-bit radix sort of the
// visible splats by depth (index order breaks ties), then a counting sort of the (tile, splat)
// pairs by tile that keeps that order. The vulkan backend does the same so both produce identical
// lists.
#pragma once

#include "render/common/thread_pool.h"
#include "render/cpu/frame.h"

namespace streetsim::cpu {

// frame->visible_ids -> frame->depth_sorted_ids (ascending depth, ties by id).
template <typename Real>
void SortByDepth(Frame<Real>* frame);

// frame->depth_sorted_ids + rects -> tile_offsets / tile_ids.
template <typename Real>
void BinTiles(ThreadPool& pool, Frame<Real>* frame);

// Sorts 32-bit keys with their values, stably (LSD radix, 11-bit digits). Exposed for tests.
void RadixSortPairs(std::vector<uint32_t>* keys, std::vector<uint32_t>* values,
                    std::vector<uint32_t>* scratch_keys, std::vector<uint32_t>* scratch_values);

}  // namespace streetsim::cpu
