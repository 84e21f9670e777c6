// Losses: values on known cases and gradients against central finite differences (double sums
// of float images, so steps are large enough to be well above float rounding).
#include <cmath>
#include <random>

#include "gtest/gtest.h"
#include "scene/train/losses.h"

namespace streetsim::train {
namespace {

std::vector<float> RandomImage(unsigned seed, size_t n) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.05f, 0.95f);
  std::vector<float> v(n);
  for (float& x : v) x = u(rng);
  return v;
}

TEST(Losses, SsimOfIdenticalImagesIsOneAndPsnrIsHigh) {
  ThreadPool pool(2);
  const std::vector<float> a = RandomImage(1, 40 * 30 * 3);
  EXPECT_NEAR(Ssim(pool, a.data(), a.data(), 40, 30, 0, nullptr), 1.0, 1e-5);
  EXPECT_GE(Psnr(a.data(), a.data(), a.size()), 99.0);
  const std::vector<float> b = RandomImage(2, a.size());
  EXPECT_LT(Ssim(pool, a.data(), b.data(), 40, 30, 0, nullptr), 0.3);
}

TEST(Losses, SsimGradientMatchesFiniteDifferences) {
  ThreadPool pool(2);
  const int w = 23, h = 17;
  std::vector<float> a = RandomImage(3, w * h * 3);
  const std::vector<float> b = RandomImage(4, w * h * 3);
  std::vector<float> grad(a.size(), 0.0f);
  Ssim(pool, a.data(), b.data(), w, h, 1.0f, grad.data());
  double num = 0, den = 0;
  for (size_t i = 0; i < a.size(); i += 7) {
    const float x = a[i];
    const float step = 1e-2f;
    a[i] = x + step;
    const double lp = Ssim(pool, a.data(), b.data(), w, h, 0, nullptr);
    a[i] = x - step;
    const double lm = Ssim(pool, a.data(), b.data(), w, h, 0, nullptr);
    a[i] = x;
    const double fd = (lp - lm) / (2 * step);
    num += (fd - grad[i]) * (fd - grad[i]);
    den += fd * fd;
  }
  const double rel = std::sqrt(num / den);
  std::printf("SSIM gradient rel. error %.2e\n", rel);
  EXPECT_LT(rel, 1e-2);
}

TEST(Losses, L1AndDepthGradients) {
  ThreadPool pool(2);
  std::vector<float> a = RandomImage(5, 300), b = RandomImage(6, 300), g(300, 0.0f);
  const double l1 = L1Loss(pool, a.data(), b.data(), a.size(), 2.0f, g.data());
  double ref = 0;
  for (size_t i = 0; i < a.size(); ++i) ref += std::abs(a[i] - b[i]);
  EXPECT_NEAR(l1, ref / 300, 1e-6);
  for (size_t i = 0; i < a.size(); ++i) EXPECT_FLOAT_EQ(g[i], (a[i] > b[i] ? 2.0f : -2.0f) / 300);

  std::vector<float> depth = {5.0f, 30.0f, 90.0f, 12.0f};
  const std::vector<DepthSample> samples = {{0, 6.0f}, {1, 20.0f}, {2, 50.0f}, {3, 100.0f}};  // last: > 80, unused
  std::vector<float> gd(4, 0.0f);
  const double dl = DepthLoss(depth.data(), samples, 0.5f, gd.data());
  const double e0 = (5.0 - 6.0) / 80, e1 = 10.0 / 80, e2 = (80.0 - 50.0) / 80;  // render clipped at 80
  EXPECT_NEAR(dl, (e0 * e0 + e1 * e1 + e2 * e2) / 3, 1e-7);
  EXPECT_NEAR(gd[0], 0.5 * 2 * e0 / 3 / 80, 1e-8);
  EXPECT_NEAR(gd[1], 0.5 * 2 * e1 / 3 / 80, 1e-8);
  EXPECT_EQ(gd[2], 0.0f);  // clipped: no gradient
  EXPECT_EQ(gd[3], 0.0f);
}

}  // namespace
}  // namespace streetsim::train
