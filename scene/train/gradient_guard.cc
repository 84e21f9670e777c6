#include "scene/train/gradient_guard.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"

namespace streetsim::train {
namespace {

// Per-Gaussian arrays of the gradient and their widths; an empty array (e.g. no screen means on a
// backend that does not fill them) is skipped.
struct Column {
  float* data;
  size_t width;
};

// Whether any value is nan or inf (all exponent bits set), as an integer reduction the compiler
// vectorises: the common case, every value finite, is one streaming pass.
bool AnyNonFinite(const float* v, size_t n) {
  uint32_t bad = 0;
  for (size_t i = 0; i < n; ++i) {
    uint32_t bits;
    std::memcpy(&bits, v + i, sizeof bits);
    bad |= static_cast<uint32_t>((bits & 0x7f800000u) == 0x7f800000u);
  }
  return bad != 0;
}

// Gaussians [b, e) in every column.
bool AnyNonFinite(const Column* cols, int ncols, size_t b, size_t e) {
  for (int c = 0; c < ncols; ++c) {
    if (AnyNonFinite(cols[c].data + b * cols[c].width, (e - b) * cols[c].width)) return true;
  }
  return false;
}

}  // namespace

NonFiniteRows ZeroNonFiniteGradientRows(size_t n, GaussianGrads* grads, ThreadPool& pool) {
  NonFiniteRows result;
  if (n == 0) return result;
  Column cols[6];
  int ncols = 0;
  for (std::vector<float>* v : {&grads->means, &grads->log_scales, &grads->rotations, &grads->opacity_logits,
                                &grads->sh, &grads->means2d}) {
    if (v->size() >= n && v->size() % n == 0) cols[ncols++] = Column{v->data(), v->size() / n};
  }
  std::atomic<size_t> rows{0};
  std::atomic<int64_t> first{INT64_MAX};
  pool.ParallelFor(static_cast<int64_t>(n), 4096, [&](int64_t b, int64_t e, int) {
    if (!AnyNonFinite(cols, ncols, b, e)) return;  // rows are looked at only in a chunk with a bad value
    size_t local = 0;
    int64_t local_first = INT64_MAX;
    for (int64_t i = b; i < e; ++i) {
      if (!AnyNonFinite(cols, ncols, i, i + 1)) continue;
      ++local;
      local_first = std::min(local_first, i);
      for (int c = 0; c < ncols; ++c) std::fill_n(cols[c].data + i * cols[c].width, cols[c].width, 0.0f);
    }
    if (local == 0) return;
    rows += local;
    int64_t cur = first.load();
    while (local_first < cur && !first.compare_exchange_weak(cur, local_first)) {
    }
  });
  result.rows = rows.load();
  if (result.rows > 0) result.first_row = first.load();
  return result;
}

absl::Status GuardGradients(int64_t iteration, size_t n, double max_fraction, GaussianGrads* grads, ThreadPool& pool) {
  const NonFiniteRows bad = ZeroNonFiniteGradientRows(n, grads, pool);
  if (bad.rows == 0) return absl::OkStatus();
  if (static_cast<double>(bad.rows) > max_fraction * static_cast<double>(n)) {
    return absl::InternalError(absl::StrCat("training diverged at iteration ", iteration, ": ", bad.rows, " of ", n,
                                            " Gaussians have a non-finite gradient (first: ", bad.first_row,
                                            "); resume from the last checkpoint with lower learning rates"));
  }
  static std::atomic<int64_t> steps_dropping{0};  // process-wide: the log is for a person, not a test
  if (steps_dropping++ % 100 != 0) return absl::OkStatus();
  LOG(WARNING) << "iteration " << iteration << ": " << bad.rows << " Gaussian(s) with a non-finite gradient (first: "
               << bad.first_row << ") skip this step (logged every 100th time)";
  return absl::OkStatus();
}

absl::Status CheckFiniteNetworkGradient(int64_t iteration, const char* what, const float* grad, size_t n,
                                        ThreadPool& pool) {
  std::atomic<int64_t> first{INT64_MAX};
  pool.ParallelFor(static_cast<int64_t>(n), 1 << 18, [&](int64_t b, int64_t e, int) {
    if (!AnyNonFinite(grad + b, static_cast<size_t>(e - b))) return;
    int64_t i = b;
    while (i < e && std::isfinite(grad[i])) ++i;
    int64_t cur = first.load();
    while (i < cur && !first.compare_exchange_weak(cur, i)) {
    }
  });
  if (first.load() == INT64_MAX) return absl::OkStatus();
  return absl::InternalError(absl::StrCat("training diverged at fine iteration ", iteration, ": the ", what,
                                          "'s gradient is not finite (first at parameter ", first.load(), " of ", n,
                                          "); its parameters were not stepped: resume from the last checkpoint with "
                                          "lower learning rates"));
}

}  // namespace streetsim::train
