// LiDAR training losses (scene/train/lidar_losses.h): values on hand-made rays, and gradients
// against central finite differences on random range images.
#include "scene/train/lidar_losses.h"

#include <cmath>
#include <functional>
#include <random>
#include <vector>

#include "gtest/gtest.h"

namespace streetsim::train {
namespace {

struct Rays {
  std::vector<float> range_sum, alpha, intensity_sum, real_range, real_intensity;
};

// n rays, about a third without a real return; alpha from 0.02 to 0.98 (both sides of the 0.1
// floor, never within 0.01 of it), rendered values kept away from the targets (no L1 kink inside
// a finite-difference step).
Rays RandomRays(unsigned seed, size_t n) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  Rays r;
  for (size_t p = 0; p < n; ++p) {
    float a = 0.02f + 0.96f * u(rng);
    if (std::abs(a - 0.1f) < 0.01f) a += 0.03f;
    const bool hit = u(rng) > 0.33f;
    const float real = hit ? 3.0f + 40.0f * u(rng) : 0.0f;
    const float real_i = hit ? u(rng) : 0.0f;
    const float off = (u(rng) > 0.5f ? 1.0f : -1.0f) * (0.5f + 3.0f * u(rng));
    const float range = std::max(1.0f, (hit ? real : 10.0f) + off);
    const float inten = std::clamp(real_i + (u(rng) > 0.5f ? 0.2f : -0.2f), 0.0f, 1.0f);
    r.alpha.push_back(a);
    r.range_sum.push_back(range * a);
    r.intensity_sum.push_back(inten * a);
    r.real_range.push_back(real);
    r.real_intensity.push_back(real_i);
  }
  return r;
}

// Central differences of loss() w.r.t. every element of x, against the analytic gradient.
double MaxRelError(std::vector<float>* x, const std::vector<float>& analytic, const std::function<double()>& loss) {
  double worst = 0;
  for (size_t i = 0; i < x->size(); ++i) {
    const float v = (*x)[i];
    const float h = 1e-4f * std::max(1.0f, std::abs(v));  // below every kink distance of RandomRays
    const float vp = v + h, vm = v - h;
    (*x)[i] = vp;
    const double lp = loss();
    (*x)[i] = vm;
    const double lm = loss();
    (*x)[i] = v;
    const double fd = (lp - lm) / (static_cast<double>(vp) - vm);
    worst = std::max(worst, std::abs(fd - analytic[i]) / std::max(1e-3, std::abs(fd)));
  }
  return worst;
}

constexpr float kWeight = 1.7f;

TEST(LidarLosses, RangeL1GradientsMatchFiniteDifferences) {
  Rays r = RandomRays(1, 300);
  const size_t n = r.alpha.size();
  std::vector<float> d_sum(n, 0.0f), d_alpha(n, 0.0f);
  LidarRangeL1(r.range_sum.data(), r.alpha.data(), r.real_range.data(), n, kWeight, d_sum.data(), d_alpha.data());
  auto loss = [&] {
    return kWeight * LidarRangeL1(r.range_sum.data(), r.alpha.data(), r.real_range.data(), n, 1.0f, nullptr, nullptr);
  };
  EXPECT_LT(MaxRelError(&r.range_sum, d_sum, loss), 1e-3);
  EXPECT_LT(MaxRelError(&r.alpha, d_alpha, loss), 1e-3);
}

TEST(LidarLosses, ReturnBceGradientsMatchFiniteDifferences) {
  Rays r = RandomRays(2, 300);
  const size_t n = r.alpha.size();
  std::vector<float> d_alpha(n, 0.0f);
  LidarReturnBce(r.alpha.data(), r.real_range.data(), n, kWeight, d_alpha.data());
  auto loss = [&] { return kWeight * LidarReturnBce(r.alpha.data(), r.real_range.data(), n, 1.0f, nullptr); };
  EXPECT_LT(MaxRelError(&r.alpha, d_alpha, loss), 1e-3);
}

TEST(LidarLosses, IntensityL1GradientsMatchFiniteDifferences) {
  Rays r = RandomRays(3, 300);
  const size_t n = r.alpha.size();
  std::vector<float> d_sum(n, 0.0f), d_alpha(n, 0.0f);
  LidarIntensityL1(r.intensity_sum.data(), r.alpha.data(), r.real_range.data(), r.real_intensity.data(), n, kWeight,
                   d_sum.data(), d_alpha.data());
  auto loss = [&] {
    return kWeight * LidarIntensityL1(r.intensity_sum.data(), r.alpha.data(), r.real_range.data(),
                                      r.real_intensity.data(), n, 1.0f, nullptr, nullptr);
  };
  EXPECT_LT(MaxRelError(&r.intensity_sum, d_sum, loss), 1e-3);
  EXPECT_LT(MaxRelError(&r.alpha, d_alpha, loss), 1e-3);
}

TEST(LidarLosses, ValuesOnHandMadeRays) {
  // Ray 0: covered (alpha 0.8), expected range 10 against 12 -> 2. Ray 1: alpha 0.05 under the
  // floor, range_sum 0.5 (range 10) against 12 -> |0.5 - 0.6| / 0.1 = 1. Ray 2: no coverage at
  // all -> 0. Ray 3: no real return (not in the range mean).
  const std::vector<float> range_sum = {8.0f, 0.5f, 0.0f, 4.0f}, alpha = {0.8f, 0.05f, 0.0f, 0.4f},
                           real = {12.0f, 12.0f, 12.0f, 0.0f};
  std::vector<float> d_sum(4, 0.0f), d_alpha(4, 0.0f);
  EXPECT_NEAR(LidarRangeL1(range_sum.data(), alpha.data(), real.data(), 4, 1.0f, d_sum.data(), d_alpha.data()),
              (2.0 + 1.0 + 0.0) / 3, 1e-6);
  EXPECT_EQ(d_sum[3], 0.0f);
  EXPECT_EQ(d_alpha[3], 0.0f);
  // Under the floor the gradients are bounded by 1 / floor (per ray, before the mean).
  EXPECT_NEAR(d_sum[1], -1.0 / 0.1 / 3, 1e-5);
  EXPECT_NEAR(d_alpha[1], 12.0 / 0.1 / 3, 1e-4);
  // The gradients add up across calls.
  LidarRangeL1(range_sum.data(), alpha.data(), real.data(), 4, 1.0f, d_sum.data(), d_alpha.data());
  EXPECT_NEAR(d_sum[1], -2.0 / 0.1 / 3, 1e-5);
  // BCE: alpha 0.5 costs log 2 either way; clamped at 1e-3.
  const std::vector<float> a2 = {0.5f, 0.5f, 0.0f}, r2 = {5.0f, 0.0f, 5.0f};
  EXPECT_NEAR(LidarReturnBce(a2.data(), r2.data(), 3, 1.0f, nullptr), (2 * std::log(2.0) - std::log(1e-3)) / 3, 1e-5);
  // No real returns: the range and intensity terms are 0.
  const std::vector<float> none(4, 0.0f);
  EXPECT_EQ(LidarRangeL1(range_sum.data(), alpha.data(), none.data(), 4, 1.0f, nullptr, nullptr), 0.0);
  EXPECT_EQ(LidarIntensityL1(range_sum.data(), alpha.data(), none.data(), none.data(), 4, 1.0f, nullptr, nullptr), 0.0);
}

}  // namespace
}  // namespace streetsim::train
