// The serving path: static Gaussians found by the pass over the log's time range, baked once;
// dynamic ones evaluated per timestamp, once per timestamp; after the log end the last state.
#include <cmath>

#include "gtest/gtest.h"
#include "scene/field/field_eval.h"
#include "scene/field/static_skip.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

// Space-time planes vary in time only over the middle texel columns of the finest xt plane: Gaussians
// whose x falls there move, the others do not.
DeformationField BandField() {
  absl::StatusOr<DeformationField> f =
      DeformationField::Create(testing::SmallConfig(), testing::TestAabb(), {0, 2'000'000}, 7);
  EXPECT_TRUE(f.ok());
  testing::AddTimeVaryingBand(&*f, 1);
  return std::move(*f);
}

GaussianStore Gaussians(int sh_degree) {
  GaussianStore g;
  g.sh_degree = sh_degree;
  const std::vector<float> m = testing::RandomMeans<float>(400, 0, 3);
  g.Resize(400);
  g.means = m;
  for (size_t i = 0; i < 400; ++i) g.rotations[i * 4] = 1;
  for (size_t i = 0; i < g.sh.size(); ++i) g.sh[i] = 0.01f * (i % 7);
  return g;
}

TEST(StaticSkip, FindsTheMovingBandAndServesExactDeformations) {
  const DeformationField f = BandField();
  const GaussianStore g = Gaussians(1);
  ThreadPool pool(2);
  StaticSkipOptions o;
  absl::StatusOr<StaticAnalysis> a = AnalyseStatic(f, g, o, pool);
  ASSERT_TRUE(a.ok()) << a.status();
  // The band is texel columns 3 and 4 of 8 at the finest level: x in the middle 3/7 of the AABB
  // (reversed map, symmetric). Well inside it every Gaussian moves; far outside none does.
  const FieldAabb box = testing::TestAabb();
  const double cx = 0.5 * (box.min[0] + box.max[0]), ext = box.max[0] - box.min[0];
  std::vector<uint8_t> dynamic(g.size(), 0);
  for (uint32_t r : a->dynamic_rows) dynamic[r] = 1;
  int inside = 0, outside = 0;
  for (size_t i = 0; i < g.size(); ++i) {
    const double d = std::abs(g.means[i * 3] - cx) / ext;
    if (d < 0.05) {
      EXPECT_TRUE(dynamic[i]) << i;
      ++inside;
    }
    if (d > 0.4) {
      EXPECT_FALSE(dynamic[i]) << i;
      ++outside;
    }
  }
  EXPECT_GT(inside, 5);
  EXPECT_GT(outside, 5);
  EXPECT_GT(a->dynamic_rows.size(), 0u);
  EXPECT_GT(a->num_static(), 0u);

  absl::StatusOr<ServingField> sf = ServingField::Create(f, g, o, pool);
  ASSERT_TRUE(sf.ok()) << sf.status();
  EXPECT_EQ(sf->num_dynamic(), a->dynamic_rows.size());
  FieldWorkspace ws;
  const int K3 = g.sh_coeffs() * 3;
  for (int64_t t : {0, 700'000, 2'000'000}) {
    absl::StatusOr<const GaussianStore*> s = sf->At(t, pool);
    ASSERT_TRUE(s.ok());
    std::vector<float> dx(g.size() * 3), dsh(g.size() * 48);
    FieldForward<float>(f.layout(), f.params().data(), f.Query(t), g.means.data(), nullptr, g.size(), dx.data(),
                        dsh.data(), pool, ws);
    for (size_t i = 0; i < g.size(); ++i) {
      // Dynamic: the field at t (up to GEMM blocking); static: the time mean, within the thresholds.
      const double tol_m = dynamic[i] ? 1e-5 : o.motion_threshold_m, tol_sh = dynamic[i] ? 1e-5 : o.sh_threshold;
      for (int k = 0; k < 3; ++k) ASSERT_NEAR((*s)->means[i * 3 + k], g.means[i * 3 + k] + dx[i * 3 + k], tol_m);
      for (int k = 0; k < K3; ++k) ASSERT_NEAR((*s)->sh[i * K3 + k], g.sh[i * K3 + k] + dsh[i * 48 + k], tol_sh);
      ASSERT_EQ((*s)->opacity_logits[i], g.opacity_logits[i]);
    }
  }
}

TEST(StaticSkip, EvaluatesOncePerTimestampAndHoldsTheLastStateAfterTheLog) {
  ThreadPool pool(2);
  absl::StatusOr<ServingField> sf = ServingField::Create(BandField(), Gaussians(0), {}, pool);
  ASSERT_TRUE(sf.ok());
  ASSERT_TRUE(sf->At(500'000, pool).ok());
  ASSERT_TRUE(sf->At(500'000, pool).ok());  // a second camera at the same time
  EXPECT_EQ(sf->field_evaluations(), 1);
  absl::StatusOr<const GaussianStore*> end = sf->At(2'000'000, pool);
  ASSERT_TRUE(end.ok());
  const std::vector<float> at_end = (*end)->means;
  EXPECT_EQ(sf->field_evaluations(), 2);
  absl::StatusOr<const GaussianStore*> later = sf->At(9'000'000, pool);  // after the log end
  ASSERT_TRUE(later.ok());
  EXPECT_EQ(sf->field_evaluations(), 2);  // same clamped time: no new evaluation
  EXPECT_EQ((*later)->means, at_end);
}

TEST(StaticSkip, DisabledEvaluatesEveryGaussianAndBadOptionsAreRejected) {
  ThreadPool pool(2);
  StaticSkipOptions o;
  o.enabled = false;
  absl::StatusOr<ServingField> sf = ServingField::Create(BandField(), Gaussians(3), o, pool);
  ASSERT_TRUE(sf.ok());
  EXPECT_EQ(sf->num_dynamic(), sf->size());
  // Without the spatial cache and the Morton order: the same deformed scene.
  o.cache_spatial_features = false;
  o.spatial_order = false;
  absl::StatusOr<ServingField> plain = ServingField::Create(BandField(), Gaussians(3), o, pool);
  ASSERT_TRUE(plain.ok());
  absl::StatusOr<const GaussianStore*> x = sf->At(1'300'000, pool), y = plain->At(1'300'000, pool);
  ASSERT_TRUE(x.ok() && y.ok());
  for (size_t i = 0; i < (*x)->means.size(); ++i) ASSERT_NEAR((*x)->means[i], (*y)->means[i], 1e-5);
  for (size_t i = 0; i < (*x)->sh.size(); ++i) ASSERT_NEAR((*x)->sh[i], (*y)->sh[i], 1e-5);
  o.enabled = true;
  o.num_samples = 1;
  EXPECT_FALSE(ServingField::Create(BandField(), Gaussians(3), o, pool).ok());
  GaussianStore bad = Gaussians(0);
  bad.means[4] = std::nanf("");
  EXPECT_FALSE(ServingField::Create(BandField(), bad, {}, pool).ok());
}

}  // namespace
}  // namespace streetsim::field
