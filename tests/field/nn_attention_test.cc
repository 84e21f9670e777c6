// Spatio-temporal multi-head attention (scene/field/nn/attention.h): gradients against central
// differences of the double forward, float against double, T = 1 reduces to the value path, a
// brute-force reference of the forward, NaN.
#include <cmath>
#include <limits>

#include "gtest/gtest.h"
#include "scene/field/nn/attention.h"
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

template <typename T>
struct AttnRun {
  Mat<T> y, dq, dx;
  std::vector<T> dp;
};

template <typename T>
AttnRun<T> RunAttention(const AttentionSpec& s, const std::vector<T>& p, const Mat<T>& q, const Mat<T>& x,
                        const Mat<T>& w) {
  AttnRun<T> r;
  AttentionCache<T> c;
  EXPECT_TRUE(AttentionForward<T>(s, p.data(), q, x, &r.y, &c).ok());
  r.dp.assign(p.size(), T(0));
  EXPECT_TRUE(AttentionBackward<T>(s, p.data(), c, w, &r.dq, &r.dx, r.dp.data()).ok());
  return r;
}

struct Instance {
  NnLayout layout;
  AttentionSpec s;
  std::vector<double> p;
  Mat<double> q, x, w;
};

// Random weights (not the init) and a layer-norm gain / bias away from 1 / 0, so that every
// parameter's gradient is exercised.
Instance MakeInstance(int query_dim, int token_dim, int tokens, int heads, int model_dim, bool residual_norm,
                      int rows, uint64_t seed) {
  Instance in;
  in.s = *MakeAttention(&in.layout, "attn", query_dim, token_dim, tokens, heads, model_dim, residual_norm);
  std::mt19937_64 rng(seed);
  in.p.resize(in.layout.total());
  FillUniform(in.p.data(), 0, in.p.size(), -0.8, 0.8, rng);
  if (residual_norm) FillUniform(in.p.data(), in.s.norm.gain_offset, model_dim, 0.5, 1.5, rng);
  in.q = RandomMat(rows, query_dim, rng);
  in.x = RandomMat(rows, int64_t{tokens} * token_dim, rng);
  in.w = RandomMat(rows, model_dim, rng);
  return in;
}

void CheckInstance(const std::string& name, Instance& in) {
  const AttnRun<double> a = RunAttention<double>(in.s, in.p, in.q, in.x, in.w);
  std::vector<Var> vars = ParamVars(in.layout, in.p, a.dp);
  vars.push_back(InputVar("query", in.q, a.dq));
  vars.push_back(InputVar("tokens", in.x, a.dx));
  ExpectGradients(name, vars, [&] { return Dot(in.w, RunAttention<double>(in.s, in.p, in.q, in.x, in.w).y); });
  const AttnRun<float> f =
      RunAttention<float>(in.s, Cast<float>(in.p), in.q.cast<float>(), in.x.cast<float>(), in.w.cast<float>());
  ExpectFloatParamsClose(name, in.layout, f.dp, a.dp);
  ExpectFloatClose(name, "query", f.dq.data(), a.dq.data(), a.dq.size());
  ExpectFloatClose(name, "tokens", f.dx.data(), a.dx.data(), a.dx.size());
  ExpectFloatClose(name, "y", f.y.data(), a.y.data(), a.y.size());
}

TEST(NnAttention, GradientsWithResidualAndNorm) {
  // 2 heads x 4, 5 tokens of width 6, 4 rows.
  Instance in = MakeInstance(8, 6, 5, 2, 8, true, 4, 11);
  CheckInstance("attention", in);
}

TEST(NnAttention, GradientsWithoutResidual) {
  Instance in = MakeInstance(5, 3, 4, 3, 6, false, 3, 12);
  CheckInstance("attn_plain", in);
}

// The forward against a direct transcription of the formulas (per row, per head).
TEST(NnAttention, ForwardMatchesBruteForce) {
  Instance in = MakeInstance(8, 6, 5, 2, 8, true, 3, 13);
  const AttnRun<double> a = RunAttention<double>(in.s, in.p, in.q, in.x, in.w);
  const AttentionSpec& s = in.s;
  auto lin = [&](const LinearSpec& l, const Eigen::VectorXd& v) {
    Eigen::VectorXd out(l.out);
    for (int o = 0; o < l.out; ++o) {
      double acc = l.bias ? in.p[l.b_offset + o] : 0.0;
      for (int i = 0; i < l.in; ++i) acc += in.p[l.w_offset + size_t(o) * l.in + i] * v(i);
      out(o) = acc;
    }
    return out;
  };
  for (int r = 0; r < 3; ++r) {
    const Eigen::VectorXd qv = lin(s.q, in.q.row(r).transpose());
    std::vector<Eigen::VectorXd> k, v;
    for (int j = 0; j < s.tokens; ++j) {
      const Eigen::VectorXd xj = in.x.row(r).segment(j * s.token_dim, s.token_dim).transpose();
      k.push_back(lin(s.k, xj));
      v.push_back(lin(s.v, xj));
    }
    Eigen::VectorXd o = Eigen::VectorXd::Zero(s.model_dim);
    const int dh = s.head_dim();
    for (int h = 0; h < s.heads; ++h) {
      std::vector<double> e(s.tokens);
      double sum = 0;
      for (int j = 0; j < s.tokens; ++j) {
        e[j] = std::exp(qv.segment(h * dh, dh).dot(k[j].segment(h * dh, dh)) / std::sqrt(double(dh)));
        sum += e[j];
      }
      for (int j = 0; j < s.tokens; ++j) o.segment(h * dh, dh) += e[j] / sum * v[j].segment(h * dh, dh);
    }
    const Eigen::VectorXd z = lin(s.o, o) + in.q.row(r).transpose();
    const double mean = z.mean();
    const double var = (z.array() - mean).square().mean();
    for (int c = 0; c < s.model_dim; ++c) {
      const double want = (z(c) - mean) / std::sqrt(var + 1e-5) * in.p[s.norm.gain_offset + c] +
                          in.p[s.norm.bias_offset + c];
      EXPECT_NEAR(a.y(r, c), want, 1e-12) << r << " " << c;
    }
  }
}

// With one token the softmax weight is 1 whatever the query: y = LN(q + (x Wv + bv) Wo + bo), and
// the query / key projections get no gradient.
TEST(NnAttention, OneTokenReducesToTheValuePath) {
  Instance in = MakeInstance(8, 6, 1, 2, 8, true, 4, 14);
  const AttnRun<double> a = RunAttention<double>(in.s, in.p, in.q, in.x, in.w);
  Mat<double> v, u, y;
  ASSERT_TRUE(LinearApply<double>(in.s.v, in.p.data(), in.x, &v).ok());
  ASSERT_TRUE(LinearApply<double>(in.s.o, in.p.data(), v, &u).ok());
  u += in.q;
  LayerNormCache<double> nc;
  ASSERT_TRUE(LayerNormForward<double>(in.s.norm, in.p.data(), u, &y, &nc).ok());
  EXPECT_LT((a.y - y).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_FALSE(in.s.k.bias);
  for (const LinearSpec* l : {&in.s.q, &in.s.k}) {
    for (int i = 0; i < l->in * l->out; ++i) EXPECT_EQ(a.dp[l->w_offset + i], 0.0);
    if (l->bias)
      for (int i = 0; i < l->out; ++i) EXPECT_EQ(a.dp[l->b_offset + i], 0.0);
  }
  // A different query changes y only through the residual.
  Instance in2 = in;
  std::mt19937_64 rng(99);
  in2.q = RandomMat(4, 8, rng);
  const AttnRun<double> b = RunAttention<double>(in2.s, in2.p, in2.q, in2.x, in2.w);
  u = u - in.q + in2.q;
  ASSERT_TRUE(LayerNormForward<double>(in.s.norm, in.p.data(), u, &y, &nc).ok());
  EXPECT_LT((b.y - y).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(NnAttention, BadSizesAreErrors) {
  NnLayout layout;
  EXPECT_FALSE(MakeAttention(&layout, "a", 8, 6, 5, 3, 8).ok());         // 8 % 3
  EXPECT_FALSE(MakeAttention(&layout, "a", 7, 6, 5, 2, 8).ok());         // residual needs 7 == 8
  EXPECT_TRUE(MakeAttention(&layout, "a", 7, 6, 5, 2, 8, false).ok());
  EXPECT_FALSE(MakeAttention(&layout, "a", 8, 6, 0, 2, 8).ok());
  EXPECT_FALSE(MakeAttention(&layout, "a", 8, 6, 257, 2, 8).ok());
  Instance in = MakeInstance(8, 6, 5, 2, 8, true, 4, 15);
  Mat<double> y;
  AttentionCache<double> c;
  std::mt19937_64 rng(1);
  EXPECT_FALSE(AttentionForward<double>(in.s, in.p.data(), in.q, RandomMat(4, 29, rng), &y, &c).ok());
  EXPECT_FALSE(AttentionForward<double>(in.s, in.p.data(), in.q.topRows(3), in.x, &y, &c).ok());
}

// A NaN in one row's tokens makes that row NaN and leaves the others alone (no cross-row mixing,
// no value-dependent indexing).
TEST(NnAttention, NaNInputStaysInItsRow) {
  Instance in = MakeInstance(8, 6, 5, 2, 8, true, 4, 16);
  in.x(2, 7) = std::numeric_limits<double>::quiet_NaN();
  const AttnRun<double> a = RunAttention<double>(in.s, in.p, in.q, in.x, in.w);
  EXPECT_TRUE(a.y.row(2).array().isNaN().all());
  for (int r : {0, 1, 3}) {
    EXPECT_TRUE(a.y.row(r).array().isFinite().all()) << r;
    EXPECT_TRUE(a.dq.row(r).array().isFinite().all()) << r;
    EXPECT_TRUE(a.dx.row(r).array().isFinite().all()) << r;
  }
  Instance inf = MakeInstance(8, 6, 5, 2, 8, true, 4, 16);
  inf.q(1, 0) = std::numeric_limits<double>::infinity();
  const AttnRun<double> b = RunAttention<double>(inf.s, inf.p, inf.q, inf.x, inf.w);
  EXPECT_TRUE(b.y.row(0).array().isFinite().all());
}

}  // namespace
}  // namespace streetsim::field::nn
