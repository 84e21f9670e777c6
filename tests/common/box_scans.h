// Synthetic LiDAR scans of boxes for the tracker and actor tests (scene/init/moving_objects.h,
// scene/actors/): surface samples on a grid fixed in the level frame.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "scene/init/moving_objects.h"

namespace streetsim::testing {

// Surface samples of an axis-aligned box (sides and top) on a grid fixed in the level frame, every
// 0.15 m, as a LiDAR samples at its own angles: a box moving along x shows the same side samples
// in every scan, and only its ends move. `flag_ends` flags the faces across x, as the dynamic mask
// flags the ends of a vehicle that slides along itself.
inline void AddBox(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, bool flag_ends, bool flag_all, LevelScan* s) {
  const double step = 0.15;
  const auto grid = [&](double from, double to) {
    std::vector<double> v;
    for (double x = std::ceil(from / step) * step; x <= to; x += step) v.push_back(x);
    return v;
  };
  const auto add = [&](double x, double y, double z, bool end) {
    s->points.emplace_back(x, y, z);
    s->dynamic.push_back(flag_all || (flag_ends && end) ? 1 : 0);
  };
  for (double y : grid(lo.y(), hi.y())) {
    for (double z : grid(lo.z(), hi.z())) {
      add(lo.x(), y, z, true);
      add(hi.x(), y, z, true);
    }
  }
  for (double x : grid(lo.x() + 0.01, hi.x() - 0.01)) {
    for (double z : grid(lo.z(), hi.z())) {
      add(x, lo.y(), z, false);
      add(x, hi.y(), z, false);
    }
    for (double y : grid(lo.y(), hi.y())) add(x, y, hi.z(), false);
  }
}

// The street both tests use, 20 scans at 10 Hz from 1 s: a 12 m truck (x from TruckX(k)) at 10 m/s
// in the right lane that stops after scan 12 (then nothing flags it), a car coming the other way at
// 8 m/s (x from CarX(k)), a parked car and a 60 m wall.
inline double StreetTruckX(int k) { return -10 + 1.0 * std::min(k, 12); }
inline double StreetCarX(int k) { return 15 - 0.8 * k; }
inline int64_t StreetScanTimeUs(int k) { return 1'000'000 + 100'000 * k; }
inline std::vector<LevelScan> Street() {
  std::vector<LevelScan> scans;
  for (int k = 0; k < 20; ++k) {
    LevelScan s;
    s.frame = k;
    s.time_us = StreetScanTimeUs(k);
    AddBox({StreetTruckX(k), -4.25, 0.3}, {StreetTruckX(k) + 12, -1.75, 3.3}, k <= 12, false, &s);
    AddBox({StreetCarX(k), 4.1, 0.3}, {StreetCarX(k) + 4.5, 5.9, 1.8}, false, true, &s);
    AddBox({5, 9, 0.3}, {9.5, 10.8, 1.8}, false, false, &s);  // parked
    for (double x = -30; x <= 30; x += 0.15) {
      for (double z = 0.3; z <= 3; z += 0.3) {
        s.points.emplace_back(x, 14, z);
        s.dynamic.push_back(0);
      }
    }
    scans.push_back(std::move(s));
  }
  return scans;
}

}  // namespace streetsim::testing
