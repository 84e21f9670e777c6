// Exclusive prefix sum: block scan (256 threads x 4 items) writing block totals, the same scan
// over the totals (recursively, up to kMaxScanLevels levels = 2^40 elements), then add-back.
// Work-efficient (O(n)), subgroup-free, deterministic.
#include <algorithm>

#include "render/vulkan/stages.h"

namespace streetsim::vulkan {
namespace {

struct ScanPush {
  uint32_t n_index;
  uint32_t level;
  uint32_t data_offset;
  uint32_t sums_offset;
};

uint64_t LevelSize(uint64_t n, int level) {
  for (int l = 0; l < level; ++l) n = DivUp(n, kScanBlock);
  return n;
}

}  // namespace

int ScanLevels(uint64_t capacity) {
  int levels = 1;
  for (uint64_t n = capacity; n > kScanBlock; n = DivUp(n, kScanBlock)) ++levels;
  return levels;
}

absl::Status ScanScratch::Ensure(const Context& ctx, uint64_t max_elements) {
  for (int k = 1; k < static_cast<int>(kMaxScanLevels); ++k) {
    Buffer& b = levels_[k - 1];
    const VkDeviceSize bytes = std::max<uint64_t>(LevelSize(max_elements, k), 1) * 4;
    if (!b.valid()) {
      auto created = Buffer::Create(ctx, bytes, Buffer::Kind::kDevice, "scan_level");
      if (!created.ok()) return created.status();
      b = *std::move(created);
    } else if (absl::Status s = b.EnsureSize(ctx, bytes); !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

void RecordScan(Recorder& rec, const Kernels& k, const ScanScratch& scratch, const Buffer& data,
                const Buffer& counts, uint32_t n_index, uint64_t capacity, uint32_t total_index,
                bool saturate, const Launch& launch) {
  const int levels = ScanLevels(capacity);
  if (levels > static_cast<int>(kMaxScanLevels)) {
    rec.Fail(absl::InvalidArgumentError("vulkan: scan larger than 2^40 elements"));
    return;
  }
  const ComputePipeline& block = saturate ? *k.scan_block_saturating : *k.scan_block;
  const ComputePipeline& add = saturate ? *k.scan_add_saturating : *k.scan_add;
  auto level_data = [&](int level) -> const Buffer& {
    return level == 0 ? data : scratch.level(level);
  };
  auto dispatch = [&](const ComputePipeline& p, int level, const Buffer& sums,
                      uint32_t sums_offset) {
    const ScanPush push{n_index, static_cast<uint32_t>(level), 0, sums_offset};
    if (launch.args != nullptr) {
      rec.DispatchIndirect(p, {&level_data(level), &sums, &counts}, push, *launch.args,
                           (launch.slot + level) * kArgsSlotBytes);
    } else {
      rec.Dispatch(p, {&level_data(level), &sums, &counts}, push,
                   GridFor(LevelSize(launch.n, level + 1)));
    }
  };
  for (int level = 0; level < levels; ++level) {
    const bool top = level == levels - 1;
    // The top level is a single block: its block total is the grand total.
    dispatch(block, level, top ? counts : scratch.level(level + 1), top ? total_index : 0);
    rec.Barrier();
  }
  for (int level = levels - 2; level >= 0; --level) {
    dispatch(add, level, scratch.level(level + 1), 0);
    rec.Barrier();
  }
}

}  // namespace streetsim::vulkan
