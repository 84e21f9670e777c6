// Central finite differences of a scalar loss over a float parameter array, for the gradient
// checks of the camera and LiDAR backward passes. Each entry is differenced at two step sizes
// (h = 1e-4 max(1, |x|) and h / 4, divided by the steps actually taken on the float grid); an
// entry whose two estimates disagree has a discontinuity inside the step (a tile edge, the 1/255
// alpha cut, a LiDAR column flip) and is marked unusable.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace streetsim::testing {

// d loss / d p[i] for every i (the h / 4 estimate); `loss()` evaluates the loss at the current p,
// which is restored after each entry.
template <typename Loss>
std::vector<double> CentralDifferences(std::vector<float>& p, const Loss& loss, std::vector<bool>* usable) {
  std::vector<double> fd(p.size());
  usable->assign(p.size(), true);
  for (size_t i = 0; i < p.size(); ++i) {
    const float x = p[i];
    auto diff = [&](double h) {
      const float xp = static_cast<float>(x + h), xm = static_cast<float>(x - h);
      p[i] = xp;
      const double lp = loss();
      p[i] = xm;
      const double lm = loss();
      p[i] = x;
      return (lp - lm) / (double(xp) - double(xm));
    };
    const double h = 1e-4 * std::max(1.0, std::abs(double(x)));
    const double d1 = diff(h), d2 = diff(h / 4);
    fd[i] = d2;
    if (std::abs(d1 - d2) > 0.02 * std::max(std::abs(d2), 1e-3)) (*usable)[i] = false;
  }
  return fd;
}

// Relative L2 error of the analytic gradient `an` against `fd` over the usable entries.
template <typename T>
double UsableRelError(const std::vector<double>& fd, const std::vector<T>& an, const std::vector<bool>& usable) {
  double num = 0, den = 0;
  for (size_t i = 0; i < fd.size(); ++i) {
    if (!usable[i]) continue;
    num += (fd[i] - an[i]) * (fd[i] - an[i]);
    den += fd[i] * fd[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

}  // namespace streetsim::testing
