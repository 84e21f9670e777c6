// Times are int64 microseconds, and a request may carry any value (a static scene accepts any
// time), so the server's sums and products of times are checked instead of overflowing.
#pragma once

#include <cstdint>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

namespace streetsim::server {

// start_us + index * step_us, or OUT_OF_RANGE when that leaves int64.
inline absl::StatusOr<int64_t> OffsetTimeUs(int64_t start_us, int64_t index, int64_t step_us) {
  int64_t offset = 0, t = 0;
  if (__builtin_mul_overflow(index, step_us, &offset) || __builtin_add_overflow(start_us, offset, &t)) {
    return absl::OutOfRangeError(absl::StrCat("time ", start_us, " us + ", index, " x ", step_us,
                                              " us leaves the int64 microsecond range"));
  }
  return t;
}

}  // namespace streetsim::server
