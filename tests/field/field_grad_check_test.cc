// Gradient checks of the field's backward pass: central finite differences of the double forward
// against the analytic gradients (double and float), relative L2 error per parameter group, on a
// small field (every parameter) and on the spec's real sizes (sampled parameters, 3 Gaussians).
#include <cmath>
#include <cstdio>
#include <functional>
#include <random>

#include "gtest/gtest.h"
#include "scene/field/field_eval.h"
#include "scene/field/field_regularizers.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::Group;
using testing::ParamGroups;
using testing::RandomMeans;
using testing::RandomParams;
using testing::RelError;
using testing::SmallConfig;
using testing::TestQuery;

struct Problem {
  FieldLayout L;
  std::vector<double> params, means, w_dx, w_dsh;
  FieldQuery q;
  size_t n = 0;
};

Problem MakeProblem(const FieldConfig& c, size_t n, uint64_t seed) {
  Problem p;
  p.L = FieldLayout::Make(c);
  p.params = RandomParams<double>(c, p.L, seed);
  p.means = RandomMeans<double>(n, n / 4, seed + 7);
  p.n = n;
  p.q = TestQuery(0.37);
  testing::RandomOutputGrads(n, seed + 3, &p.w_dx, &p.w_dsh);
  return p;
}

// L = sum w_dx . Δx + sum w_dsh . ΔSH, double.
double Loss(const Problem& p, const std::vector<double>& params, const std::vector<double>& means, ThreadPool& pool,
            FieldWorkspace& ws) {
  std::vector<double> dx(p.n * 3), dsh(p.n * kShOutputs);
  FieldForward<double>(p.L, params.data(), p.q, means.data(), nullptr, p.n, dx.data(), dsh.data(), pool, ws);
  double l = 0;
  for (size_t i = 0; i < dx.size(); ++i) l += p.w_dx[i] * dx[i];
  for (size_t i = 0; i < dsh.size(); ++i) l += p.w_dsh[i] * dsh[i];
  return l;
}

struct Analytic {
  std::vector<double> d_params, d_means;
};

Analytic AnalyticDouble(const Problem& p, ThreadPool& pool) {
  FieldWorkspace ws;
  Analytic a;
  a.d_params.assign(p.L.total, 0.0);
  a.d_means.assign(p.n * 3, 0.0);
  FieldBackward<double>(p.L, p.params.data(), p.q, p.means.data(), p.n, p.w_dx.data(), p.w_dsh.data(),
                        a.d_params.data(), a.d_means.data(), pool, ws);
  return a;
}

Analytic AnalyticFloat(const Problem& p, ThreadPool& pool) {
  auto to_f = [](const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); };
  std::vector<float> params = to_f(p.params), means = to_f(p.means), wdx = to_f(p.w_dx), wdsh = to_f(p.w_dsh);
  std::vector<float> dp(p.L.total, 0.0f), dm(p.n * 3, 0.0f);
  FieldWorkspace ws;
  FieldBackward<float>(p.L, params.data(), p.q, means.data(), p.n, wdx.data(), wdsh.data(), dp.data(), dm.data(), pool,
                       ws);
  return {std::vector<double>(dp.begin(), dp.end()), std::vector<double>(dm.begin(), dm.end())};
}

// Rounds the problem to float values so that the float and double passes see the same numbers.
void RoundToFloat(Problem* p) {
  for (std::vector<double>* v : {&p->params, &p->means, &p->w_dx, &p->w_dsh})
    for (double& x : *v) x = static_cast<float>(x);
}

void CheckAll(Problem& p, const std::vector<Group>& groups, size_t means_limit, double tol_double,
              double tol_float, const char* tag) {
  ThreadPool pool(2);
  FieldWorkspace ws;
  RoundToFloat(&p);
  const Analytic ad = AnalyticDouble(p, pool);
  const Analytic af = AnalyticFloat(p, pool);
  auto f = [&] { return Loss(p, p.params, p.means, pool, ws); };
  for (const Group& g : groups) {
    int excluded = 0;
    const double e = RelError(p.params, g.index, ad.d_params, f, &excluded);
    double num = 0, den = 0;
    for (size_t i : g.index) {
      num += (af.d_params[i] - ad.d_params[i]) * (af.d_params[i] - ad.d_params[i]);
      den += ad.d_params[i] * ad.d_params[i];
    }
    const double ef = std::sqrt(num / std::max(den, 1e-300));
    std::printf("[%s] %-15s %6zu params: double vs FD %.2e (excluded %d), float vs double %.2e\n", tag,
                g.name.c_str(), g.index.size(), e, excluded, ef);
    EXPECT_LT(e, tol_double) << g.name;
    EXPECT_LT(ef, tol_float) << g.name;
    EXPECT_LE(excluded, static_cast<int>(g.index.size() / 10 + 1)) << g.name;
  }
  std::vector<size_t> mi;
  for (size_t i = 0; i < std::min(means_limit, p.n * 3); ++i) mi.push_back(i);
  auto fm = [&] { return Loss(p, p.params, p.means, pool, ws); };
  int excluded = 0;
  const double e = RelError(p.means, mi, ad.d_means, fm, &excluded);
  double num = 0, den = 0;
  for (size_t i : mi) {
    num += (af.d_means[i] - ad.d_means[i]) * (af.d_means[i] - ad.d_means[i]);
    den += ad.d_means[i] * ad.d_means[i];
  }
  const double ef = std::sqrt(num / den);
  std::printf("[%s] %-15s %6zu params: double vs FD %.2e (excluded %d), float vs double %.2e\n", tag, "means",
              mi.size(), e, excluded, ef);
  EXPECT_LT(e, tol_double);
  EXPECT_LT(ef, tol_float);
  EXPECT_GT(den, 0);  // the position path is exercised
}

TEST(FieldGradCheck, SmallFieldEveryParameter) {
  Problem p = MakeProblem(SmallConfig(), 24, 11);
  CheckAll(p, ParamGroups(p.L), 1000, 1e-6, 1e-4, "small");
}

TEST(FieldGradCheck, HalfTimeRangeAndTimeAtTheBorder) {
  // S3Gaussian's time map and a time exactly on the last time sample.
  FieldConfig c = SmallConfig();
  c.full_time_range = false;
  Problem p = MakeProblem(c, 12, 5);
  p.q.time_coord = 1.0;
  CheckAll(p, ParamGroups(p.L), 1000, 1e-6, 1e-4, "t=1");
}

TEST(FieldGradCheck, SpecSizesSampledParameters) {
  Problem p = MakeProblem(FieldConfig{}, 3, 23);
  ThreadPool pool(2);
  const Analytic ad = AnalyticDouble(p, pool);
  // 40 entries per group: touched texels (non-zero gradient) for the planes, any for the MLP.
  std::mt19937_64 rng(3);
  std::vector<Group> groups;
  for (Group& g : ParamGroups(p.L)) {
    std::vector<size_t> cand;
    const bool plane = g.name.find("planes") != std::string::npos;
    for (size_t i : g.index)
      if (!plane || ad.d_params[i] != 0) cand.push_back(i);
    std::shuffle(cand.begin(), cand.end(), rng);
    cand.resize(std::min<size_t>(cand.size(), 40));
    ASSERT_FALSE(cand.empty()) << g.name;
    groups.push_back({g.name, cand});
  }
  CheckAll(p, groups, 9, 1e-6, 1e-4, "spec");
}

TEST(FieldGradCheck, Regularizers) {
  const FieldConfig c = SmallConfig();
  const FieldLayout L = FieldLayout::Make(c);
  std::vector<double> params = RandomParams<double>(c, L, 9);
  ThreadPool pool(2);
  RegularizerWeights w{0.3, 0.7, 0.2};  // all terms visible in the check
  std::vector<double> grad(L.total, 0.0);
  const RegularizerLosses l = PlaneRegularizers<double>(L, params.data(), w, grad.data(), pool);
  EXPECT_GT(l.spatial_smoothness, 0);
  EXPECT_GT(l.time_smoothness, 0);
  EXPECT_GT(l.l1_time, 0);
  std::vector<size_t> idx(L.grid_size);
  for (size_t i = 0; i < idx.size(); ++i) idx[i] = i;
  auto f = [&] { return PlaneRegularizers<double>(L, params.data(), w, nullptr, pool).weighted; };
  int excluded = 0;
  const double e = RelError(params, idx, grad, f, &excluded);
  std::printf("[reg] planes %zu params: double vs FD %.2e (excluded %d)\n", idx.size(), e, excluded);
  EXPECT_LT(e, 1e-6);
  EXPECT_LE(excluded, 2);
  for (size_t i = L.grid_size; i < L.total; ++i) ASSERT_EQ(grad[i], 0.0);
}

TEST(FieldGradCheck, RegularizerValuesByHand) {
  // One level, time resolution 3: S2 of a space-time plane is the mean squared second difference.
  FieldConfig c = SmallConfig();
  c.multires = {1};
  c.time_resolution = 3;
  const FieldLayout L = FieldLayout::Make(c);
  std::vector<double> params(L.total, 1.0);
  const PlaneInfo& xt = L.planes[2];
  const size_t row = static_cast<size_t>(xt.width) * L.channels;
  for (size_t i = 0; i < row; ++i) params[xt.offset + row + i] = 1.5;  // middle time row: D = -1
  ThreadPool pool(1);
  const RegularizerLosses l = PlaneRegularizers<double>(L, params.data(), RegularizerWeights{}, nullptr, pool);
  EXPECT_DOUBLE_EQ(l.time_smoothness, 1.0);
  EXPECT_DOUBLE_EQ(l.l1_time, 0.5 / 3);  // mean |1 - P| over 3 rows, one of them off by 0.5
  EXPECT_DOUBLE_EQ(l.spatial_smoothness, 0.0);
}

}  // namespace
}  // namespace streetsim::field
