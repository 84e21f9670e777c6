#include "scene/field/spatial_order.h"

#include <algorithm>
#include <cmath>

namespace streetsim::field {

namespace {
// Spreads the low 10 bits of x so that two zero bits separate each.
inline uint32_t Spread3(uint32_t x) {
  x &= 0x3ff;
  x = (x | (x << 16)) & 0x030000ff;
  x = (x | (x << 8)) & 0x0300f00f;
  x = (x | (x << 4)) & 0x030c30c3;
  x = (x | (x << 2)) & 0x09249249;
  return x;
}
}  // namespace

std::vector<uint32_t> SpatialOrder(const FieldAabb& aabb, const float* means, size_t n, const uint32_t* rows,
                                   ThreadPool& pool) {
  std::vector<uint64_t> keyed(n);  // code << 32 | row: one sort of 64-bit keys
  double scale[3];
  for (int k = 0; k < 3; ++k) scale[k] = 1023.0 / (aabb.max[k] - aabb.min[k]);
  pool.ParallelFor(static_cast<int64_t>(n), 16384, [&](int64_t b, int64_t e, int) {
    for (int64_t r = b; r < e; ++r) {
      const uint32_t i = rows ? rows[r] : static_cast<uint32_t>(r);
      uint32_t code = 0;
      for (int k = 0; k < 3; ++k) {
        double q = (means[static_cast<size_t>(i) * 3 + k] - aabb.min[k]) * scale[k];
        q = q > 0 ? q : 0;  // NaN -> 0
        q = q < 1023 ? q : 1023;
        code |= Spread3(static_cast<uint32_t>(q)) << k;
      }
      keyed[r] = (static_cast<uint64_t>(code) << 32) | i;
    }
  });
  std::sort(keyed.begin(), keyed.end());
  std::vector<uint32_t> out(n);
  for (size_t r = 0; r < n; ++r) out[r] = static_cast<uint32_t>(keyed[r]);
  return out;
}

}  // namespace streetsim::field
