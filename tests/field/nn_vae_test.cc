// Variational sampler and KL term (scene/field/nn/vae_sampler.h): gradients against central
// differences, the KL against its closed form and a numeric integral, inference z = mu, NaN.
#include <cmath>
#include <limits>

#include "gtest/gtest.h"
#include "scene/field/nn/vae_sampler.h"
#include "tests/field/nn_test_util.h"

namespace streetsim::field::nn {
namespace {

using testing::Dot;
using testing::ExpectFloatClose;
using testing::ExpectGradients;
using testing::InputVar;
using testing::RandomMat;

template <typename T>
Mat<T> RunSample(const VaeSpec& s, const Mat<T>& x, const Mat<T>& eps, const Mat<T>& w, Mat<T>* dx) {
  Mat<T> z;
  VaeCache<T> c;
  EXPECT_TRUE(VaeSampleForward<T>(s, x, eps, &z, &c).ok());
  EXPECT_TRUE(VaeSampleBackward<T>(s, c, w, dx).ok());
  return z;
}

TEST(NnVae, SampleAndGradients) {
  std::mt19937_64 rng(31);
  const VaeSpec s = *MakeVae(4);
  Mat<double> x = RandomMat(5, 8, rng, -1.5, 1.5);
  const Mat<double> eps = RandomMat(5, 4, rng, -2, 2), w = RandomMat(5, 4, rng);
  Mat<double> dx, unused;
  const Mat<double> z = RunSample<double>(s, x, eps, w, &dx);
  EXPECT_NEAR(z(3, 2), x(3, 2) + std::exp(0.5 * x(3, 6)) * eps(3, 2), 1e-14);
  ExpectGradients("vae_sample", {InputVar("mu_logvar", x, dx)},
                  [&] { return Dot(w, RunSample<double>(s, x, eps, w, &unused)); });
  Mat<float> dxf;
  const Mat<float> zf = RunSample<float>(s, x.cast<float>(), eps.cast<float>(), w.cast<float>(), &dxf);
  ExpectFloatClose("vae_sample", "z", zf.data(), z.data(), z.size());
  ExpectFloatClose("vae_sample", "mu_logvar", dxf.data(), dx.data(), dx.size());
  // eps = 0: the sample is the mean, as at inference.
  Mat<double> zm, z0;
  ASSERT_TRUE(VaeMean<double>(s, x, &zm).ok());
  EXPECT_EQ(zm, x.leftCols(4));
  z0 = RunSample<double>(s, x, Mat<double>::Zero(5, 4), w, &unused);
  EXPECT_EQ(z0, zm);
}

TEST(NnVae, KlValueAndGradient) {
  std::mt19937_64 rng(32);
  const VaeSpec s = *MakeVae(3);
  Mat<double> x = RandomMat(4, 6, rng, -1.5, 1.5);
  const double weight = 0.37;
  double kl = 0;
  Mat<double> g = Mat<double>::Zero(4, 6);
  ASSERT_TRUE(VaeKl<double>(s, x, weight, &kl, &g).ok());
  // Closed form, and zero exactly at the prior.
  double want = 0;
  for (int r = 0; r < 4; ++r)
    for (int i = 0; i < 3; ++i) {
      const double mu = x(r, i), var = std::exp(x(r, 3 + i));
      want += 0.5 * (mu * mu + var - std::log(var) - 1);
    }
  EXPECT_NEAR(kl, weight * want, 1e-14);
  double kl0 = 1;
  ASSERT_TRUE(VaeKl<double>(s, Mat<double>::Zero(2, 6), 1.0, &kl0, nullptr).ok());
  EXPECT_EQ(kl0, 0.0);
  // One dimension by numeric integration of q log(q / p) (trapezoid over +-12 sigma).
  {
    const double mu = 0.7, lv = -0.4, sd = std::exp(0.5 * lv);
    double integral = 0;
    const int n = 200000;
    const double lo = mu - 12 * sd, hi = mu + 12 * sd, dxs = (hi - lo) / n;
    for (int i = 0; i <= n; ++i) {
      const double v = lo + i * dxs;
      const double lq = -0.5 * std::log(2 * M_PI) - std::log(sd) - 0.5 * (v - mu) * (v - mu) / (sd * sd);
      const double lp = -0.5 * std::log(2 * M_PI) - 0.5 * v * v;
      integral += (i == 0 || i == n ? 0.5 : 1.0) * std::exp(lq) * (lq - lp) * dxs;
    }
    Mat<double> one(1, 2);
    one << mu, lv;
    double k1 = 0;
    ASSERT_TRUE(VaeKl<double>(*MakeVae(1), one, 1.0, &k1, nullptr).ok());
    EXPECT_NEAR(k1, integral, 1e-8);
  }
  // Gradient (added to what is there).
  ExpectGradients("vae_kl", {InputVar("mu_logvar", x, g)}, [&] {
    double v = 0;
    EXPECT_TRUE(VaeKl<double>(s, x, weight, &v, nullptr).ok());
    return v;
  });
  Mat<double> g2 = Mat<double>::Ones(4, 6);
  ASSERT_TRUE(VaeKl<double>(s, x, weight, &kl, &g2).ok());
  EXPECT_LT((g2 - g - Mat<double>::Ones(4, 6)).cwiseAbs().maxCoeff(), 1e-15);
  Mat<float> gf = Mat<float>::Zero(4, 6);
  float klf = 0;
  ASSERT_TRUE(VaeKl<float>(s, x.cast<float>(), static_cast<float>(weight), &klf, &gf).ok());
  EXPECT_NEAR(klf, kl, 1e-5 * std::abs(kl));
  ExpectFloatClose("vae_kl", "mu_logvar", gf.data(), g.data(), g.size());
}

TEST(NnVae, BadShapesAndNaN) {
  EXPECT_FALSE(MakeVae(0).ok());
  const VaeSpec s = *MakeVae(2);
  Mat<double> z;
  VaeCache<double> c;
  EXPECT_FALSE(VaeSampleForward<double>(s, Mat<double>::Zero(3, 3), Mat<double>::Zero(3, 2), &z, &c).ok());
  EXPECT_FALSE(VaeSampleForward<double>(s, Mat<double>::Zero(3, 4), Mat<double>::Zero(2, 2), &z, &c).ok());
  double kl = 0;
  Mat<double> wrong = Mat<double>::Zero(3, 3);
  EXPECT_FALSE(VaeKl<double>(s, Mat<double>::Zero(3, 4), 1.0, &kl, &wrong).ok());
  Mat<double> x = Mat<double>::Zero(3, 4);
  x(1, 3) = std::numeric_limits<double>::quiet_NaN();
  ASSERT_TRUE(VaeSampleForward<double>(s, x, Mat<double>::Ones(3, 2), &z, &c).ok());
  EXPECT_TRUE(std::isnan(z(1, 1)));
  EXPECT_TRUE(z.row(0).array().isFinite().all());
  ASSERT_TRUE(VaeKl<double>(s, x, 1.0, &kl, nullptr).ok());
  EXPECT_TRUE(std::isnan(kl));
}

}  // namespace
}  // namespace streetsim::field::nn
