// The trainer glue (deform, back-propagate to the field and the canonical means, Δ sparsity
// terms) against double finite differences, and the field's Adam groups and schedules.
#include <cmath>
#include <functional>
#include <random>

#include "gtest/gtest.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/field_adam.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::CentralDifference;

constexpr int kDegree = 1;  // active SH degree of the render: 4 coefficients per channel

struct GlueCase {
  DeformationField field;
  std::vector<float> means, sh, w_means, w_sh;  // w_*: dL/d(rendered means, SH at kDegree)
  FieldHyper hyper;
  double t = 0.4;
  size_t n = 20;
};

GlueCase MakeGlueCase() {
  GlueCase s;
  const FieldConfig c = testing::SmallConfig();
  absl::StatusOr<DeformationField> f = DeformationField::Create(c, testing::TestAabb(), {0, 10}, 2);
  EXPECT_TRUE(f.ok());
  s.field = std::move(*f);
  s.field.mutable_params() = testing::RandomParams<float>(c, s.field.layout(), 6);
  s.means = testing::RandomMeans<float>(s.n, 2, 4);
  std::mt19937 rng(2);
  std::normal_distribution<float> nd;
  s.sh.resize(s.n * 48);
  s.w_means.resize(s.n * 3);
  s.w_sh.resize(s.n * 12);
  for (float& v : s.sh) v = 0.3f * nd(rng);
  for (float& v : s.w_means) v = nd(rng);
  for (float& v : s.w_sh) v = nd(rng);
  s.hyper.lambda_dx = 0.05;  // large enough to show in the check
  s.hyper.lambda_dsh = 0.05;
  return s;
}

// The loss the glue differentiates, in double.
double Loss(const GlueCase& s, const std::vector<double>& params, const std::vector<double>& means) {
  ThreadPool pool(1);
  FieldWorkspace ws;
  std::vector<double> dx(s.n * 3), dsh(s.n * 48);
  FieldForward<double>(s.field.layout(), params.data(), s.field.QueryAtCoordinate(s.t), means.data(), nullptr, s.n,
                       dx.data(), dsh.data(), pool, ws);
  double l = 0, adx = 0, adsh = 0;
  for (size_t i = 0; i < s.n * 3; ++i) {
    l += s.w_means[i] * (means[i] + dx[i]);
    adx += std::abs(dx[i]);
  }
  for (size_t i = 0; i < s.n; ++i)
    for (int k = 0; k < 48; ++k) {
      if (k < 12) l += s.w_sh[i * 12 + k] * (s.sh[i * 48 + k] + dsh[i * 48 + k]);
      adsh += std::abs(dsh[i * 48 + k]);
    }
  return l + s.hyper.lambda_dx * adx / (3.0 * s.n) + s.hyper.lambda_dsh * adsh / (48.0 * s.n);
}

double RelErrorFd(std::vector<double>& x, size_t begin, size_t end, const std::vector<float>& analytic,
                  const std::function<double()>& f) {
  double num = 0, den = 0;
  for (size_t i = begin; i < end; ++i) {
    const double a = CentralDifference(x, i, 1e-6, f), b = CentralDifference(x, i, 2e-6, f);
    if (std::abs(a - b) > 1e-5 * std::max(1e-3, std::abs(a))) continue;  // a kink (ReLU, |.|) inside the step
    num += (analytic[i - begin] - a) * (analytic[i - begin] - a);
    den += a * a;
  }
  return std::sqrt(num / den);
}

TEST(DeformedScene, ForwardAddsTheDeformationsAndTheViewSwapsThem) {
  GlueCase s = MakeGlueCase();
  ThreadPool pool(2);
  FieldWorkspace ws;
  DeformedScene d;
  ASSERT_TRUE(DeformScene(s.field, s.t, {s.n, s.means.data(), s.sh.data()}, pool, ws, &d).ok());
  for (size_t i = 0; i < s.n * 3; ++i) EXPECT_FLOAT_EQ(d.means[i], s.means[i] + d.dx[i]);
  for (size_t i = 0; i < s.n * 48; ++i) EXPECT_FLOAT_EQ(d.sh[i], s.sh[i] + d.dsh[i]);
  GaussianParamsView canonical;
  canonical.n = s.n;
  canonical.means = s.means.data();
  canonical.sh = s.sh.data();
  canonical.sh_stride = 16;
  canonical.sh_degree = kDegree;
  const GaussianParamsView v = DeformedParamsView(canonical, d);
  EXPECT_EQ(v.means, d.means.data());
  EXPECT_EQ(v.sh, d.sh.data());
  EXPECT_EQ(v.sh_degree, kDegree);
}

TEST(DeformedScene, BackwardMatchesFiniteDifferences) {
  GlueCase s = MakeGlueCase();
  ThreadPool pool(2);
  FieldWorkspace ws;
  DeformedScene d;
  const CanonicalView cv{s.n, s.means.data(), s.sh.data()};
  ASSERT_TRUE(DeformScene(s.field, s.t, cv, pool, ws, &d).ok());
  GaussianGrads g;
  g.means = s.w_means;
  g.sh = s.w_sh;
  std::vector<float> d_field;
  absl::StatusOr<DeformLosses> losses = DeformBackward(s.field, cv, d, kDegree, s.hyper, pool, ws, &g, &d_field);
  ASSERT_TRUE(losses.ok()) << losses.status();
  EXPECT_GT(losses->dx_l1, 0);
  EXPECT_GT(losses->dsh_l1, 0);
  EXPECT_EQ(g.sh, s.w_sh);  // the SH gradient passes through unchanged

  std::vector<double> params(s.field.params().begin(), s.field.params().end());
  std::vector<double> means(s.means.begin(), s.means.end());
  auto f = [&] { return Loss(s, params, means); };
  const FieldLayout& L = s.field.layout();
  const double e_grid = RelErrorFd(params, 0, L.grid_size, {d_field.begin(), d_field.begin() + L.grid_size}, f);
  const double e_mlp = RelErrorFd(params, L.grid_size, L.total, {d_field.begin() + L.grid_size, d_field.end()}, f);
  const double e_means = RelErrorFd(means, 0, means.size(), g.means, f);
  std::printf("glue: grid %.2e  mlp %.2e  canonical means %.2e (float analytic vs double FD)\n", e_grid, e_mlp,
              e_means);
  EXPECT_LT(e_grid, 1e-4);
  EXPECT_LT(e_mlp, 1e-4);
  EXPECT_LT(e_means, 1e-4);

  g.sh.resize(3);  // wrong size: an error, not a crash
  EXPECT_FALSE(DeformBackward(s.field, cv, d, kDegree, s.hyper, pool, ws, &g, &d_field).ok());
}

TEST(FieldAdam, ScheduleAndGroups) {
  const FieldHyper h;
  const double E = 3.9;
  FieldLrs a = FieldLearningRates(h, 0, E), b = FieldLearningRates(h, 30000, E), c = FieldLearningRates(h, 50000, E);
  EXPECT_NEAR(a.grid, 1.6e-4 * E, 1e-12);
  EXPECT_NEAR(a.deformation, 1.6e-5 * E, 1e-12);
  EXPECT_NEAR(b.grid, 1.6e-5 * E, 1e-12);
  EXPECT_NEAR(b.deformation, 1.6e-6 * E, 1e-12);
  EXPECT_NEAR(c.grid, b.grid, 1e-15);
  EXPECT_NEAR(FieldLearningRates(h, 15000, E).grid, std::sqrt(1.6e-4 * 1.6e-5) * E, 1e-12);  // log-linear
  // --field-lr-scale multiplies both groups at every step; --field-lr-decay-iterations moves the
  // end of the decay.
  FieldHyper fast;
  fast.lr_scale = 4;
  fast.lr_decay_steps = 6000;
  EXPECT_NEAR(FieldLearningRates(fast, 0, E).grid, 4 * 1.6e-4 * E, 1e-12);
  EXPECT_NEAR(FieldLearningRates(fast, 0, E).deformation, 4 * 1.6e-5 * E, 1e-12);
  EXPECT_NEAR(FieldLearningRates(fast, 3000, E).grid, 4 * std::sqrt(1.6e-4 * 1.6e-5) * E, 1e-12);
  EXPECT_NEAR(FieldLearningRates(fast, 9000, E).deformation, 4 * 1.6e-6 * E, 1e-12);

  const FieldLayout L = FieldLayout::Make(testing::SmallConfig());
  std::vector<float> p(L.total, 1.0f), g(L.total);
  for (size_t i = 0; i < g.size(); ++i) g[i] = (i % 2) ? 0.5f : -2.0f;
  FieldAdamState st;
  ThreadPool pool(2);
  FieldAdamStep(L, p.data(), g.data(), &st, {0.01, 0.001}, pool);
  EXPECT_EQ(st.step, 1);
  // Adam's first step moves every parameter by lr against the sign of its gradient.
  for (size_t i = 0; i < L.total; ++i) {
    const double lr = i < L.grid_size ? 0.01 : 0.001;
    ASSERT_NEAR(p[i], 1.0 - lr * (g[i] > 0 ? 1 : -1), 1e-6) << i;
  }
}

}  // namespace
}  // namespace streetsim::field
