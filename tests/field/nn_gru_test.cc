// GRU cell and bidirectional GRU (scene/field/nn/gru_cell.h, bi_gru.h): gradients against central
// differences of the double forward, float against double, the reverse direction is the forward
// one on reversed tokens, NaN.
#include <cmath>
#include <limits>

#include "gtest/gtest.h"
#include "scene/field/nn/bi_gru.h"
#include "scene/field/nn/gru_cell.h"
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
struct CellRun {
  Mat<T> h, dx, dh_prev;
  std::vector<T> dp;
};

template <typename T>
CellRun<T> RunCell(const GruCellSpec& s, const std::vector<T>& p, const Mat<T>& x, const Mat<T>& h_prev,
                   const Mat<T>& w) {
  CellRun<T> r;
  GruCellCache<T> c;
  EXPECT_TRUE(GruCellForward<T>(s, p.data(), x, h_prev, &r.h, &c).ok());
  r.dp.assign(p.size(), T(0));
  EXPECT_TRUE(GruCellBackward<T>(s, p.data(), c, w, &r.dx, &r.dh_prev, r.dp.data()).ok());
  return r;
}

TEST(NnGruCell, MatchesTheEquationsAndGradients) {
  std::mt19937_64 rng(21);
  NnLayout layout;
  const GruCellSpec s = *MakeGruCell(&layout, "cell", 4, 3);
  std::vector<double> p(layout.total());
  FillUniform(p.data(), 0, p.size(), -0.9, 0.9, rng);
  Mat<double> x = RandomMat(5, 4, rng), h = RandomMat(5, 3, rng);
  const Mat<double> w = RandomMat(5, 3, rng);
  const CellRun<double> a = RunCell<double>(s, p, x, h, w);
  // Row 1, unit 2 by hand (PyTorch's GRUCell).
  auto wih = [&](int row, int col) { return p[s.w_ih + size_t(row) * 4 + col]; };
  auto whh = [&](int row, int col) { return p[s.w_hh + size_t(row) * 3 + col]; };
  auto gate = [&](int g, bool hidden) {
    double acc = hidden ? p[s.b_hh + g] : p[s.b_ih + g];
    if (hidden) {
      for (int k = 0; k < 3; ++k) acc += whh(g, k) * h(1, k);
    } else {
      for (int k = 0; k < 4; ++k) acc += wih(g, k) * x(1, k);
    }
    return acc;
  };
  auto sig = [](double v) { return 1 / (1 + std::exp(-v)); };
  const double r = sig(gate(2, false) + gate(2, true));
  const double z = sig(gate(3 + 2, false) + gate(3 + 2, true));
  const double n = std::tanh(gate(6 + 2, false) + r * gate(6 + 2, true));
  EXPECT_NEAR(a.h(1, 2), (1 - z) * n + z * h(1, 2), 1e-12);

  std::vector<Var> vars = ParamVars(layout, p, a.dp);
  vars.push_back(InputVar("x", x, a.dx));
  vars.push_back(InputVar("h_prev", h, a.dh_prev));
  ExpectGradients("gru_cell", vars, [&] { return Dot(w, RunCell<double>(s, p, x, h, w).h); });
  const CellRun<float> f = RunCell<float>(s, Cast<float>(p), x.cast<float>(), h.cast<float>(), w.cast<float>());
  ExpectFloatParamsClose("gru_cell", layout, f.dp, a.dp);
  ExpectFloatClose("gru_cell", "x", f.dx.data(), a.dx.data(), a.dx.size());
  ExpectFloatClose("gru_cell", "h_prev", f.dh_prev.data(), a.dh_prev.data(), a.dh_prev.size());
}

template <typename T>
struct BiRun {
  Mat<T> y, dx, last;
  std::vector<T> dp;
};

template <typename T>
BiRun<T> RunBiGru(const BiGruSpec& s, const std::vector<T>& p, const Mat<T>& x, const Mat<T>& w) {
  BiRun<T> r;
  BiGruCache<T> c;
  EXPECT_TRUE(BiGruForward<T>(s, p.data(), x, &r.y, &c).ok());
  r.last = c.last;
  r.dp.assign(p.size(), T(0));
  EXPECT_TRUE(BiGruBackward<T>(s, p.data(), c, w, &r.dx, r.dp.data()).ok());
  return r;
}

struct BiInstance {
  NnLayout layout;
  BiGruSpec s;
  std::vector<double> p;
  Mat<double> x, w;
};

BiInstance MakeBi(int tokens, int input_dim, int hidden, int out_dim, int rows, uint64_t seed) {
  BiInstance in;
  in.s = *MakeBiGru(&in.layout, "gru", tokens, input_dim, hidden, out_dim);
  std::mt19937_64 rng(seed);
  in.p.resize(in.layout.total());
  FillUniform(in.p.data(), 0, in.p.size(), -0.9, 0.9, rng);
  in.x = RandomMat(rows, int64_t{tokens} * input_dim, rng);
  in.w = RandomMat(rows, out_dim, rng);
  return in;
}

TEST(NnBiGru, Gradients) {
  BiInstance in = MakeBi(/*tokens=*/5, /*input_dim=*/4, /*hidden=*/3, /*out_dim=*/5, /*rows=*/4, 22);
  const BiRun<double> a = RunBiGru<double>(in.s, in.p, in.x, in.w);
  std::vector<Var> vars = ParamVars(in.layout, in.p, a.dp);
  vars.push_back(InputVar("tokens", in.x, a.dx));
  ExpectGradients("bi_gru", vars, [&] { return Dot(in.w, RunBiGru<double>(in.s, in.p, in.x, in.w).y); });
  const BiRun<float> f = RunBiGru<float>(in.s, Cast<float>(in.p), in.x.cast<float>(), in.w.cast<float>());
  ExpectFloatParamsClose("bi_gru", in.layout, f.dp, a.dp);
  ExpectFloatClose("bi_gru", "tokens", f.dx.data(), a.dx.data(), a.dx.size());
}

// With the reverse cell's parameters set to the forward cell's, the reverse direction's last state
// on tokens (x0..x4) equals the forward direction's on (x4..x0), and the forward one equals the
// step-by-step GruCell.
TEST(NnBiGru, ReverseDirectionIsForwardOnReversedTokens) {
  BiInstance in = MakeBi(5, 4, 3, 5, 3, 23);
  const size_t cell_size = in.s.rev.w_ih - in.s.fwd.w_ih;
  std::copy(in.p.begin() + in.s.fwd.w_ih, in.p.begin() + in.s.fwd.w_ih + cell_size, in.p.begin() + in.s.rev.w_ih);
  Mat<double> reversed(in.x.rows(), in.x.cols());
  for (int j = 0; j < 5; ++j) reversed.middleCols(j * 4, 4) = in.x.middleCols((4 - j) * 4, 4);
  const BiRun<double> a = RunBiGru<double>(in.s, in.p, in.x, in.w);
  const BiRun<double> b = RunBiGru<double>(in.s, in.p, reversed, in.w);
  EXPECT_LT((a.last.rightCols(3) - b.last.leftCols(3)).cwiseAbs().maxCoeff(), 1e-14);
  EXPECT_LT((a.last.leftCols(3) - b.last.rightCols(3)).cwiseAbs().maxCoeff(), 1e-14);
  EXPECT_GT((a.last.leftCols(3) - a.last.rightCols(3)).cwiseAbs().maxCoeff(), 1e-3);  // order matters

  Mat<double> h = Mat<double>::Zero(3, 3), next;
  GruCellCache<double> c;
  for (int j = 0; j < 5; ++j) {
    ASSERT_TRUE(GruCellForward<double>(in.s.fwd, in.p.data(), in.x.middleCols(j * 4, 4), h, &next, &c).ok());
    h = next;
  }
  EXPECT_LT((a.last.leftCols(3) - h).cwiseAbs().maxCoeff(), 1e-14);
}

TEST(NnBiGru, BadSizesAndNaN) {
  NnLayout layout;
  EXPECT_FALSE(MakeBiGru(&layout, "g", 0, 4, 3, 5).ok());
  EXPECT_FALSE(MakeBiGru(&layout, "g", 5, 4, 0, 5).ok());
  EXPECT_FALSE(MakeBiGru(&layout, "g", 5, 4, 3, 0).ok());
  BiInstance in = MakeBi(5, 4, 3, 5, 3, 24);
  Mat<double> y;
  BiGruCache<double> c;
  std::mt19937_64 rng(2);
  EXPECT_FALSE(BiGruForward<double>(in.s, in.p.data(), RandomMat(3, 19, rng), &y, &c).ok());
  in.x(1, 9) = std::numeric_limits<double>::quiet_NaN();
  const BiRun<double> a = RunBiGru<double>(in.s, in.p, in.x, in.w);
  EXPECT_TRUE(a.y.row(1).array().isNaN().any());
  for (int r : {0, 2}) {
    EXPECT_TRUE(a.y.row(r).array().isFinite().all()) << r;
    EXPECT_TRUE(a.dx.row(r).array().isFinite().all()) << r;
  }
}

}  // namespace
}  // namespace streetsim::field::nn
