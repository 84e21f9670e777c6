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

// A grayscale camera beside colour ones is compared on the render's luminance: L1 + D-SSIM of the
// luminance against the gray image, chained back to RGB, matches finite differences, and a render
// whose colour differs only in chroma (same luminance) costs nothing.
TEST(Losses, LuminanceChainsBackToRgb) {
  ThreadPool pool(2);
  const int w = 8, h = 6;
  const size_t pixels = static_cast<size_t>(w) * h;
  std::vector<float> rgb = RandomImage(11, pixels * 3), gray = RandomImage(12, pixels * 3);
  for (size_t p = 0; p < pixels; ++p) gray[p * 3 + 1] = gray[p * 3 + 2] = gray[p * 3];
  auto loss = [&](const std::vector<float>& x, float* d_rgb) {
    std::vector<float> y(pixels * 3), d_y(pixels * 3, 0.0f);
    LuminanceRgb(x.data(), pixels, y.data());
    const double l = L1Loss(pool, y.data(), gray.data(), y.size(), 1.0f, d_rgb ? d_y.data() : nullptr) +
                     0.2 * (1 - Ssim(pool, y.data(), gray.data(), w, h, d_rgb ? -0.2f : 0.0f,
                                     d_rgb ? d_y.data() : nullptr));
    if (d_rgb) LuminanceBackward(d_y.data(), pixels, d_rgb);
    return l;
  };
  std::vector<float> g(pixels * 3, 0.0f);
  loss(rgb, g.data());
  double num = 0, den = 0;
  for (size_t i = 0; i < rgb.size(); i += 5) {
    const float eps = 1e-3f;
    std::vector<float> a = rgb, b = rgb;
    a[i] += eps;
    b[i] -= eps;
    const double fd = (loss(a, nullptr) - loss(b, nullptr)) / (2 * eps);
    num += (g[i] - fd) * (g[i] - fd);
    den += fd * fd;
  }
  EXPECT_LT(std::sqrt(num / den), 2e-2);
  // Chroma alone is free: a colour render with the gray image's luminance has loss 0.
  std::vector<float> tinted(pixels * 3);
  for (size_t p = 0; p < pixels; ++p) {
    const float y = gray[p * 3];
    // R and B moved against each other so that 0.299 dR + 0.114 dB = 0.
    tinted[p * 3] = y + 0.0114f;
    tinted[p * 3 + 1] = y;
    tinted[p * 3 + 2] = y - 0.0299f;
  }
  EXPECT_LT(loss(tinted, nullptr), 1e-5);
}

}  // namespace
}  // namespace streetsim::train
