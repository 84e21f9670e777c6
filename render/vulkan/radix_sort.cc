// Stable LSD radix sort of (uint key, uint value) pairs, 4 bits per pass. Each pass: per-block
// digit histograms (digit-major), one exclusive scan over all of them, and a stable scatter.
// Written with shared memory and barriers only, so it is correct for any subgroup size.
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {
namespace {

struct RadixPush {
  uint32_t n_index;
  uint32_t shift;
};

}  // namespace

int RadixPasses(int bits) { return (bits + static_cast<int>(kRadixBits) - 1) / kRadixBits; }

int RecordRadixSort(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                    const SortBuffers& bufs, const Buffer& counts, uint32_t n_index,
                    uint32_t hist_n_index, uint64_t capacity, int first_bit, int bits,
                    const Launch& blocks, const Launch& hist_scan) {
  const int passes = RadixPasses(bits);
  const uint64_t hist_capacity = kRadix * DivUp(capacity, kSortBlock);
  auto dispatch = [&](const ComputePipeline& p, std::initializer_list<const Buffer*> buffers,
                      const RadixPush& push) {
    if (blocks.args != nullptr) {
      rec.DispatchIndirect(p, buffers, push, *blocks.args, blocks.slot * kArgsSlotBytes);
    } else {
      rec.Dispatch(p, buffers, push, GridFor(DivUp(blocks.n, kSortBlock)));
    }
  };
  for (int pass = 0; pass < passes; ++pass) {
    const int in = pass & 1, out = in ^ 1;
    const RadixPush push{n_index, static_cast<uint32_t>(first_bit + pass * kRadixBits)};
    dispatch(*k.radix_hist, {bufs.keys[in], bufs.hist, &counts}, push);
    rec.Barrier();
    RecordScan(rec, k, scratch, *bufs.hist, counts, hist_n_index, hist_capacity, kCountSink,
               /*saturate=*/false, hist_scan);
    if (bufs.vals[0] != nullptr) {
      dispatch(*k.radix_scatter,
               {bufs.keys[in], bufs.vals[in], bufs.keys[out], bufs.vals[out], bufs.hist, &counts},
               push);
    } else {
      // The value bindings are not accessed by the keys-only variant; any buffer fills them.
      dispatch(*k.radix_scatter_keys_only,
               {bufs.keys[in], bufs.keys[in], bufs.keys[out], bufs.keys[out], bufs.hist, &counts},
               push);
    }
    rec.Barrier();
  }
  return passes & 1;
}

}  // namespace streetsim::vulkan
