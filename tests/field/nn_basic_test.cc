// Linear, layer norm, activations and Fourier time tokens (scene/field/nn): analytic gradients
// against central differences of the double forward, float against double, bad shapes, NaN.
#include <cmath>
#include <limits>

#include "gtest/gtest.h"
#include "scene/field/nn/activation.h"
#include "scene/field/nn/fourier_time.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"
#include "tests/field/nn_test_util.h"

namespace streetsim::field::nn {
namespace {

using testing::Cast;
using testing::Dot;
using testing::ExpectFloatClose;
using testing::ExpectFloatParamsClose;
using testing::ExpectGradients;
using testing::InputVar;
using testing::ParamVars;
using testing::RandomMat;
using testing::Var;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

TEST(NnLayout, HandsOutConsecutiveNamedBlocks) {
  NnLayout layout;
  const LinearSpec a = *MakeLinear(&layout, "a", 3, 2);
  const LinearSpec b = *MakeLinear(&layout, "b", 2, 4, /*bias=*/false);
  const LayerNormSpec n = *MakeLayerNorm(&layout, "n", 4);
  EXPECT_EQ(a.w_offset, 0u);
  EXPECT_EQ(a.b_offset, 6u);
  EXPECT_EQ(b.w_offset, 8u);
  EXPECT_EQ(n.gain_offset, 16u);
  EXPECT_EQ(n.bias_offset, 20u);
  EXPECT_EQ(layout.total(), 24u);
  ASSERT_EQ(layout.blocks().size(), 5u);
  EXPECT_EQ(layout.blocks()[2].name, "b.weight");
  EXPECT_FALSE(MakeLinear(&layout, "bad", 0, 2).ok());
  EXPECT_FALSE(MakeLayerNorm(&layout, "bad", 4, 0.0).ok());
}

// --- linear ---

template <typename T>
struct LinearRun {
  Mat<T> y, dx;
  std::vector<T> dp;
};

template <typename T>
LinearRun<T> RunLinear(const LinearSpec& s, const std::vector<T>& p, const Mat<T>& x, const Mat<T>& w) {
  LinearRun<T> r;
  LinearCache<T> c;
  EXPECT_TRUE(LinearForward<T>(s, p.data(), x, &r.y, &c).ok());
  r.dp.assign(p.size(), T(0));
  EXPECT_TRUE(LinearBackward<T>(s, p.data(), c, w, &r.dx, r.dp.data()).ok());
  return r;
}

TEST(NnLinear, GradientsMatchFiniteDifferencesAndFloat) {
  std::mt19937_64 rng(1);
  NnLayout layout;
  const LinearSpec s = *MakeLinear(&layout, "lin", 5, 4);
  std::vector<double> p(layout.total());
  InitLinear(s, rng, p.data());
  Mat<double> x = RandomMat(6, 5, rng);
  const Mat<double> w = RandomMat(6, 4, rng);
  const LinearRun<double> a = RunLinear<double>(s, p, x, w);
  // y = x W^T + b, checked against a direct sum.
  EXPECT_NEAR(a.y(2, 3), x.row(2).dot(Eigen::Map<const RowVec<double>>(p.data() + s.w_offset + 3 * 5, 5)) +
                             p[s.b_offset + 3], 1e-12);
  std::vector<Var> vars = ParamVars(layout, p, a.dp);
  vars.push_back(InputVar("x", x, a.dx));
  ExpectGradients("linear", vars, [&] { return Dot(w, RunLinear<double>(s, p, x, w).y); });
  const LinearRun<float> f = RunLinear<float>(s, Cast<float>(p), x.cast<float>(), w.cast<float>());
  ExpectFloatParamsClose("linear", layout, f.dp, a.dp);
  ExpectFloatClose("linear", "x", f.dx.data(), a.dx.data(), a.dx.size());
  ExpectFloatClose("linear", "y", f.y.data(), a.y.data(), a.y.size());
}

TEST(NnLinear, WrongShapesAreErrorsNotCrashes) {
  NnLayout layout;
  const LinearSpec s = *MakeLinear(&layout, "lin", 5, 4);
  std::vector<double> p(layout.total(), 0.1), g(layout.total(), 0.0);
  Mat<double> y, dx;
  LinearCache<double> c;
  const absl::Status st = LinearForward<double>(s, p.data(), Mat<double>::Zero(3, 4), &y, &c);
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(st.message()).find("linear"), std::string::npos) << st;
  ASSERT_TRUE(LinearForward<double>(s, p.data(), Mat<double>::Zero(3, 5), &y, &c).ok());
  EXPECT_FALSE(LinearBackward<double>(s, p.data(), c, Mat<double>::Zero(2, 4), &dx, g.data()).ok());
  // A NaN input row gives a NaN output row, the others are untouched.
  Mat<double> x = Mat<double>::Ones(3, 5);
  x(1, 4) = kNaN;
  ASSERT_TRUE(LinearForward<double>(s, p.data(), x, &y, &c).ok());
  EXPECT_TRUE(y.row(1).array().isNaN().all());
  EXPECT_TRUE(y.row(0).array().isFinite().all() && y.row(2).array().isFinite().all());
  ASSERT_TRUE(LinearBackward<double>(s, p.data(), c, Mat<double>::Ones(3, 4), &dx, g.data()).ok());
  EXPECT_TRUE(dx.array().isFinite().all());  // dx = dy W does not see x
}

// --- layer norm ---

template <typename T>
struct NormRun {
  Mat<T> y, dx;
  std::vector<T> dp;
};

template <typename T>
NormRun<T> RunNorm(const LayerNormSpec& s, const std::vector<T>& p, const Mat<T>& x, const Mat<T>& w) {
  NormRun<T> r;
  LayerNormCache<T> c;
  EXPECT_TRUE(LayerNormForward<T>(s, p.data(), x, &r.y, &c).ok());
  r.dp.assign(p.size(), T(0));
  EXPECT_TRUE(LayerNormBackward<T>(s, p.data(), c, w, &r.dx, r.dp.data()).ok());
  return r;
}

TEST(NnLayerNorm, NormalisesAndGradientsMatch) {
  std::mt19937_64 rng(2);
  NnLayout layout;
  const LayerNormSpec s = *MakeLayerNorm(&layout, "norm", 7);
  std::vector<double> p(layout.total());
  InitLayerNorm(s, p.data());
  Mat<double> x = RandomMat(5, 7, rng, -2, 3);
  const Mat<double> w = RandomMat(5, 7, rng);
  // With gain 1 and bias 0 every row has mean 0 and (biased) variance 1 - eps/(var + eps).
  const NormRun<double> unit = RunNorm<double>(s, p, x, w);
  for (int r = 0; r < 5; ++r) {
    EXPECT_NEAR(unit.y.row(r).mean(), 0.0, 1e-12);
    EXPECT_NEAR(unit.y.row(r).squaredNorm() / 7, 1.0, 1e-4);
  }
  // Learned gain and bias away from the identity so that their gradients matter.
  FillUniform(p.data(), 0, p.size(), -1.5, 1.5, rng);
  const NormRun<double> a = RunNorm<double>(s, p, x, w);
  std::vector<Var> vars = ParamVars(layout, p, a.dp);
  vars.push_back(InputVar("x", x, a.dx));
  ExpectGradients("layer_norm", vars, [&] { return Dot(w, RunNorm<double>(s, p, x, w).y); });
  const NormRun<float> f = RunNorm<float>(s, Cast<float>(p), x.cast<float>(), w.cast<float>());
  ExpectFloatParamsClose("layer_norm", layout, f.dp, a.dp);
  ExpectFloatClose("layer_norm", "x", f.dx.data(), a.dx.data(), a.dx.size());
}

TEST(NnLayerNorm, NaNRowStaysInItsRow) {
  NnLayout layout;
  const LayerNormSpec s = *MakeLayerNorm(&layout, "norm", 4);
  std::vector<double> p(layout.total());
  InitLayerNorm(s, p.data());
  Mat<double> x = Mat<double>::Ones(3, 4);
  x(0, 1) = 2;
  x(1, 2) = kNaN;
  x(2, 3) = -1;
  Mat<double> y, dx;
  LayerNormCache<double> c;
  ASSERT_TRUE(LayerNormForward<double>(s, p.data(), x, &y, &c).ok());
  EXPECT_TRUE(y.row(1).array().isNaN().all());
  EXPECT_TRUE(y.row(0).array().isFinite().all());
  EXPECT_TRUE(y.row(2).array().isFinite().all());
  std::vector<double> g(p.size(), 0.0);
  ASSERT_TRUE(LayerNormBackward<double>(s, p.data(), c, Mat<double>::Ones(3, 4), &dx, g.data()).ok());
  EXPECT_TRUE(dx.row(1).array().isNaN().all());
  EXPECT_TRUE(dx.row(0).array().isFinite().all());
}

// --- activations ---

template <typename T>
Mat<T> RunActivation(Activation a, const Mat<T>& x, const Mat<T>& w, Mat<T>* dx) {
  Mat<T> y;
  ActivationCache<T> c;
  ActivationForward<T>(a, x, &y, &c);
  EXPECT_TRUE(ActivationBackward<T>(a, c, w, dx).ok());
  return y;
}

TEST(NnActivation, GradientsMatchForEveryKind) {
  for (Activation act : {Activation::kRelu, Activation::kGelu, Activation::kSilu}) {
    std::mt19937_64 rng(3);
    Mat<double> x = RandomMat(4, 9, rng, -3, 3);
    const Mat<double> w = RandomMat(4, 9, rng);
    Mat<double> dx;
    const Mat<double> y = RunActivation<double>(act, x, w, &dx);
    Mat<double> unused;
    ExpectGradients(ActivationName(act), {InputVar("x", x, dx)},
                    [&] { return Dot(w, RunActivation<double>(act, x, w, &unused)); });
    Mat<float> dxf;
    const Mat<float> yf = RunActivation<float>(act, x.cast<float>(), w.cast<float>(), &dxf);
    ExpectFloatClose(ActivationName(act), "y", yf.data(), y.data(), y.size());
    ExpectFloatClose(ActivationName(act), "x", dxf.data(), dx.data(), dx.size());
  }
  // Known values.
  EXPECT_EQ(ActivationValue(Activation::kRelu, -2.0), 0.0);
  EXPECT_EQ(ActivationValue(Activation::kRelu, 2.0), 2.0);
  EXPECT_NEAR(ActivationValue(Activation::kGelu, 1.0), 0.8413447460685429, 1e-12);
  EXPECT_NEAR(ActivationValue(Activation::kSilu, 1.0), 0.7310585786300049, 1e-12);
  EXPECT_EQ(*ParseActivation("gelu"), Activation::kGelu);
  EXPECT_FALSE(ParseActivation("tanh").ok());
}

TEST(NnActivation, NaNPropagates) {
  for (Activation act : {Activation::kRelu, Activation::kGelu, Activation::kSilu}) {
    EXPECT_TRUE(std::isnan(ActivationValue(act, kNaN))) << ActivationName(act);
    EXPECT_TRUE(std::isnan(ActivationDerivative(act, kNaN))) << ActivationName(act);
    // The block forms too (relu and silu are vectorised separately from the scalar forms).
    Mat<double> x(1, 3), dx;
    x << -1, kNaN, 2;
    const Mat<double> y = RunActivation<double>(act, x, Mat<double>::Ones(1, 3), &dx);
    EXPECT_TRUE(std::isnan(y(0, 1)) && std::isnan(dx(0, 1))) << ActivationName(act);
    EXPECT_TRUE(std::isfinite(y(0, 0)) && std::isfinite(y(0, 2)) && std::isfinite(dx(0, 2))) << ActivationName(act);
    Mat<float> dxf;
    const Mat<float> yf = RunActivation<float>(act, x.cast<float>(), Mat<float>::Ones(1, 3), &dxf);
    EXPECT_TRUE(std::isnan(yf(0, 1)) && std::isnan(dxf(0, 1))) << ActivationName(act);
  }
}

// --- Fourier time tokens ---

template <typename T>
struct FourierRun {
  Mat<T> tokens, dt, df;
};

template <typename T>
FourierRun<T> RunFourier(const FourierTimeSpec& s, const Mat<T>& t, const Mat<T>& f, const Mat<T>& w) {
  FourierRun<T> r;
  FourierTimeCache<T> c;
  EXPECT_TRUE(FourierTimeForward<T>(s, t, f, &r.tokens, &c).ok());
  EXPECT_TRUE(FourierTimeBackward<T>(s, c, w, &r.dt, &r.df).ok());
  return r;
}

TEST(NnFourierTime, TokenLayoutAndGradients) {
  std::mt19937_64 rng(4);
  const FourierTimeSpec s = *MakeFourierTime(/*frequencies=*/4, /*tokens=*/3, /*feature_dim=*/5);
  EXPECT_EQ(s.token_dim(), 13);
  Mat<double> t = RandomMat(6, 3, rng);
  Mat<double> f = RandomMat(6, 15, rng);
  const Mat<double> w = RandomMat(6, 39, rng);
  const FourierRun<double> a = RunFourier<double>(s, t, f, w);
  // Row 2, token 1: sin(2^k pi t), cos(2^k pi t), features.
  const double t21 = t(2, 1);
  EXPECT_NEAR(a.tokens(2, 13 + 2), std::sin(4 * M_PI * t21), 1e-12);
  EXPECT_NEAR(a.tokens(2, 13 + 4 + 3), std::cos(8 * M_PI * t21), 1e-12);
  EXPECT_EQ(a.tokens(2, 13 + 8 + 4), f(2, 5 + 4));
  ExpectGradients("fourier_time", {InputVar("times", t, a.dt), InputVar("features", f, a.df)},
                  [&] { return Dot(w, RunFourier<double>(s, t, f, w).tokens); });
  const FourierRun<float> fl = RunFourier<float>(s, t.cast<float>(), f.cast<float>(), w.cast<float>());
  ExpectFloatClose("fourier_time", "tokens", fl.tokens.data(), a.tokens.data(), a.tokens.size());
  ExpectFloatClose("fourier_time", "times", fl.dt.data(), a.dt.data(), a.dt.size());
  EXPECT_FALSE(MakeFourierTime(-1, 3, 5).ok());
  EXPECT_FALSE(MakeFourierTime(4, 0, 5).ok());
  Mat<double> out;
  FourierTimeCache<double> c;
  EXPECT_FALSE(FourierTimeForward<double>(s, t, RandomMat(6, 14, rng), &out, &c).ok());
}

TEST(NnFourierTime, NaNTimeGivesNaNFeaturesOnlyInItsToken) {
  const FourierTimeSpec s = *MakeFourierTime(2, 2, 1);
  Mat<double> t(1, 2);
  t << kNaN, 0.25;
  Mat<double> f(1, 2);
  f << 1, 2;
  Mat<double> out;
  FourierTimeCache<double> c;
  ASSERT_TRUE(FourierTimeForward<double>(s, t, f, &out, &c).ok());
  EXPECT_TRUE(out.leftCols(4).array().isNaN().all());
  EXPECT_EQ(out(0, 4), 1.0);
  EXPECT_TRUE(out.rightCols(5).array().isFinite().all());
}

}  // namespace
}  // namespace streetsim::field::nn
