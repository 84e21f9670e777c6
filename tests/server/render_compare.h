// Comparisons of two served frames of one view that may differ by float rounding (a kernel on
// another device, multiply-adds fused or summed in another order): field_device_test.cc argues the
// bounds of ExpectFramesWithinRounding.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "streetsim/v1/common.pb.h"

namespace streetsim::testing {

// The largest difference of two RAW RGB images in 8-bit levels, and the fraction of bytes that differ.
struct ByteDiff {
  int max = 0;
  double fraction = 0;
};
inline ByteDiff CompareRgb(const std::string& a, const std::string& b) {
  EXPECT_EQ(a.size(), b.size());
  ByteDiff d;
  const size_t n = std::min(a.size(), b.size());
  for (size_t i = 0; i < n; ++i) {
    const int e = std::abs(int(uint8_t(a[i])) - int(uint8_t(b[i])));
    d.max = std::max(d.max, e);
    d.fraction += e > 0;
  }
  d.fraction /= std::max<size_t>(n, 1);
  return d;
}

// Of two F32 depth images (metres): the largest |a - b| / (1 + |b|), and the fraction of pixels
// where it exceeds 1e-4.
struct DepthDiff {
  double max = 0, fraction = 0;
};
inline DepthDiff CompareDepth(const std::string& a, const std::string& b) {
  EXPECT_EQ(a.size(), b.size());
  const size_t n = std::min(a.size(), b.size()) / sizeof(float);
  std::vector<float> x(n), y(n);
  std::memcpy(x.data(), a.data(), n * sizeof(float));
  std::memcpy(y.data(), b.data(), n * sizeof(float));
  DepthDiff d;
  for (size_t i = 0; i < n; ++i) {
    const double e = std::abs(double(x[i]) - y[i]) / (1.0 + std::abs(double(y[i])));
    d.max = std::max(d.max, e);
    d.fraction += e > 1e-4;
  }
  d.fraction /= std::max<size_t>(n, 1);
  return d;
}

// Two frames of one view within the rounding bounds argued in field_device_test.cc (RGB within 2
// levels on under 1 % of the bytes, depth within 1e-2 relative on under 1 % of the pixels beyond
// 1e-4); prints them.
inline void ExpectFramesWithinRounding(const v1::SensorFrame& a, const v1::SensorFrame& b, const std::string& tag) {
  const ByteDiff rgb = CompareRgb(a.rgb().data(), b.rgb().data());
  EXPECT_LE(rgb.max, 2) << tag;
  EXPECT_LT(rgb.fraction, 0.01) << tag;
  const DepthDiff depth = CompareDepth(a.depth().data(), b.depth().data());
  EXPECT_LT(depth.max, 1e-2) << tag;
  EXPECT_LT(depth.fraction, 0.01) << tag;
  std::printf("%s: RGB max %d levels (%.4f %% of bytes), depth max %.2e (%.4f %% of pixels > 1e-4)\n", tag.c_str(),
              rgb.max, 100 * rgb.fraction, depth.max, 100 * depth.fraction);
}

}  // namespace streetsim::testing
