// Synthetic LiDAR scans of boxes for the tracker and actor tests (scene/init/moving_objects.h,
// scene/actors/): surface samples on a grid fixed in the level frame.
#pragma once

#include <cmath>
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

}  // namespace streetsim::testing
