// The field's forward semantics against an independent naive reference (PyTorch grid_sample with
// align_corners=True and border padding, S3Gaussian's reversed AABB map), time mapping, row
// subsets, thread-count independence and bad input.
#include <cmath>
#include <limits>
#include <random>

#include "gtest/gtest.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_eval.h"
#include "scene/field/hexplane_kernels.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::RandomMeans;
using testing::RandomParams;
using testing::SmallConfig;
using testing::TestAabb;
using testing::TestQuery;

// Written from the spec's text, one Gaussian at a time, without the module's helpers.
void NaiveForward(const FieldConfig& c, const FieldLayout& L, const std::vector<double>& P, const FieldQuery& q,
                  const double* xyz, double* dx, double* dsh) {
  double coord[4];
  for (int k = 0; k < 3; ++k) {
    // aabb = [max; min]; p = (x - aabb[0]) * 2 / (aabb[1] - aabb[0]) - 1
    coord[k] = (xyz[k] - q.aabb_max[k]) * 2 / (q.aabb_min[k] - q.aabb_max[k]) - 1;
  }
  coord[3] = q.time_coord;
  std::vector<double> f;
  for (int l = 0; l < L.num_levels; ++l) {
    std::vector<double> fl(c.channels, 1.0);
    for (int pl = 0; pl < 6; ++pl) {
      const PlaneInfo& pi = L.planes[l * 6 + pl];
      auto texel = [&](int v, int u, int ch) { return P[pi.offset + (size_t(v) * pi.width + u) * c.channels + ch]; };
      const double x = std::clamp((coord[kPlaneCoords[pl][0]] + 1) / 2 * (pi.width - 1), 0.0, pi.width - 1.0);
      const double y = std::clamp((coord[kPlaneCoords[pl][1]] + 1) / 2 * (pi.height - 1), 0.0, pi.height - 1.0);
      const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
      const int x1 = std::min(x0 + 1, pi.width - 1), y1 = std::min(y0 + 1, pi.height - 1);
      const double ax = x - x0, ay = y - y0;
      for (int ch = 0; ch < c.channels; ++ch) {
        fl[ch] *= (1 - ax) * (1 - ay) * texel(y0, x0, ch) + ax * (1 - ay) * texel(y0, x1, ch) +
                  (1 - ax) * ay * texel(y1, x0, ch) + ax * ay * texel(y1, x1, ch);
      }
    }
    f.insert(f.end(), fl.begin(), fl.end());
  }
  auto linear = [&](const DenseInfo& d, const std::vector<double>& in, bool relu_in) {
    std::vector<double> out(d.out);
    for (int o = 0; o < d.out; ++o) {
      double s = P[d.b_offset + o];
      for (int i = 0; i < d.in; ++i) s += P[d.w_offset + size_t(o) * d.in + i] * (relu_in ? std::max(0.0, in[i]) : in[i]);
      out[o] = s;
    }
    return out;
  };
  const std::vector<double> h = linear(L.trunk, f, false);
  const std::vector<double> p1 = linear(L.pos1, h, true), p2 = linear(L.pos2, p1, true);
  const std::vector<double> s1 = linear(L.sh1, h, true), s2 = linear(L.sh2, s1, true);
  for (int k = 0; k < 3; ++k) dx[k] = p2[k];
  for (int k = 0; k < kShOutputs; ++k) dsh[k] = s2[k];
}

TEST(FieldEval, MatchesNaiveReferenceInsideOutsideAndOnTheBorder) {
  for (bool full : {true, false}) {
    FieldConfig c = SmallConfig();
    c.full_time_range = full;
    const FieldLayout L = FieldLayout::Make(c);
    const std::vector<double> P = RandomParams<double>(c, L, 4);
    std::vector<double> means = RandomMeans<double>(40, 10, 8);
    const FieldAabb a = TestAabb();
    // Exactly on the corners (x = max -> p = -1 -> texel 0) and far outside.
    for (int k = 0; k < 3; ++k) {
      means.push_back(a.max[k]);
    }
    for (int k = 0; k < 3; ++k) means.push_back(a.min[k]);
    for (int k = 0; k < 3; ++k) means.push_back(a.min[k] - 100);
    const size_t n = means.size() / 3;
    ThreadPool pool(2);
    FieldWorkspace ws;
    for (double t : {-1.0, -0.3, 0.0, 0.61, 1.0, 1.7}) {
      const FieldQuery q = TestQuery(t);
      std::vector<double> dx(n * 3), dsh(n * kShOutputs);
      FieldForward<double>(L, P.data(), q, means.data(), nullptr, n, dx.data(), dsh.data(), pool, ws);
      for (size_t i = 0; i < n; ++i) {
        double rdx[3], rdsh[kShOutputs];
        NaiveForward(c, L, P, q, &means[i * 3], rdx, rdsh);
        for (int k = 0; k < 3; ++k) ASSERT_NEAR(dx[i * 3 + k], rdx[k], 1e-12) << "gaussian " << i << " t " << t;
        for (int k = 0; k < kShOutputs; ++k) ASSERT_NEAR(dsh[i * kShOutputs + k], rdsh[k], 1e-12);
      }
    }
  }
}

TEST(FieldEval, TapsFollowGridSampleAlignCornersBorder) {
  using internal::MakeTap;
  EXPECT_EQ(MakeTap(-1.0, 5).i0, 0);
  EXPECT_EQ(MakeTap(-1.0, 5).w, 0.0);
  EXPECT_EQ(MakeTap(0.0, 5).i0, 2);  // centre of 5 samples: texel 2 exactly
  EXPECT_EQ(MakeTap(0.0, 5).w, 0.0);
  EXPECT_EQ(MakeTap(1.0, 5).i0, 3);  // last texel = upper tap with weight 1
  EXPECT_EQ(MakeTap(1.0, 5).w, 1.0);
  EXPECT_EQ(MakeTap(2.5, 5).w, 1.0);           // clamped at the border ...
  EXPECT_EQ(MakeTap(2.5, 5).dpx_dp, 0.0);      // ... with zero derivative
  EXPECT_EQ(MakeTap(0.5, 5).dpx_dp, 2.0);      // (R - 1) / 2 inside
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(MakeTap(nan, 5).i0, 0);            // bad input never indexes out of the plane
  EXPECT_EQ(MakeTap(std::numeric_limits<double>::infinity(), 5).i0, 3);
}

TEST(FieldEval, TimeMappingAndClampAfterTheLogEnd) {
  const FieldTimeRange tr{1'000'000, 6'000'000};
  for (bool full : {true, false}) {
    FieldConfig c = SmallConfig();
    c.full_time_range = full;
    absl::StatusOr<DeformationField> f = DeformationField::Create(c, TestAabb(), tr, 1);
    ASSERT_TRUE(f.ok()) << f.status();
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(1'000'000), full ? -1.0 : 0.0);
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(3'500'000), full ? 0.0 : 0.5);
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(6'000'000), 1.0);
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(60'000'000), 1.0);  // after the end: the last state
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(-5), full ? -1.0 : 0.0);
    EXPECT_DOUBLE_EQ(f->TimeCoordinate(std::numeric_limits<int64_t>::min()), full ? -1.0 : 0.0);
  }
  absl::StatusOr<DeformationField> one = DeformationField::Create(SmallConfig(), TestAabb(), {5, 5}, 1);
  ASSERT_TRUE(one.ok());
  EXPECT_DOUBLE_EQ(one->TimeCoordinate(99), -1.0);  // a one-frame log: a single state
}

TEST(FieldEval, SpecInitIsTimeInvariant) {
  // Space-time planes start at 1: the product ignores time until training moves them.
  absl::StatusOr<DeformationField> f = DeformationField::Create(SmallConfig(), TestAabb(), {0, 100}, 3);
  ASSERT_TRUE(f.ok());
  const std::vector<float> means = RandomMeans<float>(30, 5, 1);
  ThreadPool pool(2);
  FieldWorkspace ws;
  std::vector<float> a(30 * 3), b(30 * 3), sa(30 * 48), sb(30 * 48);
  FieldForward<float>(f->layout(), f->params().data(), f->Query(0), means.data(), nullptr, 30, a.data(), sa.data(),
                      pool, ws);
  FieldForward<float>(f->layout(), f->params().data(), f->Query(77), means.data(), nullptr, 30, b.data(), sb.data(),
                      pool, ws);
  EXPECT_EQ(a, b);
  EXPECT_EQ(sa, sb);
}

TEST(FieldEval, RowSubsetAndThreadCountGiveIdenticalResults) {
  const FieldConfig c = SmallConfig();
  const FieldLayout L = FieldLayout::Make(c);
  const std::vector<float> P = RandomParams<float>(c, L, 2);
  const size_t n = 5000;  // several chunks and backward blocks
  const std::vector<float> means = RandomMeans<float>(n, 300, 3);
  const FieldQuery q = TestQuery(0.2);
  ThreadPool p1(1), p2(2);
  FieldWorkspace w1, w2;
  std::vector<float> dx1(n * 3), dx2(n * 3), s1(n * 48), s2(n * 48);
  FieldForward<float>(L, P.data(), q, means.data(), nullptr, n, dx1.data(), s1.data(), p1, w1);
  FieldForward<float>(L, P.data(), q, means.data(), nullptr, n, dx2.data(), s2.data(), p2, w2);
  EXPECT_EQ(dx1, dx2);
  EXPECT_EQ(s1, s2);
  std::vector<uint32_t> rows = {4999, 7, 7, 1234, 0};
  std::vector<float> rdx(rows.size() * 3), rs(rows.size() * 48);
  FieldForward<float>(L, P.data(), q, means.data(), rows.data(), rows.size(), rdx.data(), rs.data(), p2, w2);
  // Same values up to the GEMM's blocking (the product's summation order depends on the rows).
  for (size_t r = 0; r < rows.size(); ++r) {
    for (int k = 0; k < 3; ++k) EXPECT_NEAR(rdx[r * 3 + k], dx1[rows[r] * 3 + k], 1e-5);
    for (int k = 0; k < 48; ++k) EXPECT_NEAR(rs[r * 48 + k], s1[rows[r] * 48 + k], 1e-5);
  }
  // Backward: plane gradients are scattered per plane in row order, so they do not depend on the
  // thread count; MLP gradients are summed per thread (last bits may differ).
  std::vector<float> g_dx(n * 3), g_dsh(n * 48);
  std::mt19937 rng(1);
  std::normal_distribution<float> nd;
  for (float& v : g_dx) v = nd(rng);
  for (float& v : g_dsh) v = nd(rng);
  std::vector<float> gp1(L.total, 0), gp2(L.total, 0), gm1(n * 3, 0), gm2(n * 3, 0);
  FieldBackward<float>(L, P.data(), q, means.data(), n, g_dx.data(), g_dsh.data(), gp1.data(), gm1.data(), p1, w1);
  FieldBackward<float>(L, P.data(), q, means.data(), n, g_dx.data(), g_dsh.data(), gp2.data(), gm2.data(), p2, w2);
  for (size_t i = 0; i < L.grid_size; ++i) ASSERT_EQ(gp1[i], gp2[i]) << i;
  for (size_t i = L.grid_size; i < L.total; ++i) ASSERT_NEAR(gp1[i], gp2[i], 1e-4 * (1 + std::abs(gp1[i]))) << i;
  EXPECT_EQ(gm1, gm2);
}

TEST(FieldEval, CachedSpatialFeaturesGiveTheSameField) {
  const FieldConfig c = SmallConfig();
  const FieldLayout L = FieldLayout::Make(c);
  const std::vector<double> P = RandomParams<double>(c, L, 12);
  const size_t n = 700;
  const std::vector<double> means = RandomMeans<double>(n, 50, 13);
  ThreadPool pool(2);
  FieldWorkspace ws;
  std::vector<uint32_t> rows(n / 2);
  for (size_t r = 0; r < rows.size(); ++r) rows[r] = static_cast<uint32_t>((r * 7) % n);
  std::vector<double> spatial(rows.size() * L.feature_dim());
  SpatialFeatures<double>(L, P.data(), TestQuery(0), means.data(), rows.data(), rows.size(), spatial.data(), pool);
  for (double t : {-1.0, 0.3, 1.0}) {
    std::vector<double> a(rows.size() * 3), b(rows.size() * 3), sa(rows.size() * 48), sb(rows.size() * 48);
    FieldForward<double>(L, P.data(), TestQuery(t), means.data(), rows.data(), rows.size(), a.data(), sa.data(), pool,
                         ws);
    FieldForwardCached<double>(L, P.data(), TestQuery(t), means.data(), rows.data(), spatial.data(), rows.size(),
                               b.data(), sb.data(), pool, ws);
    for (size_t i = 0; i < a.size(); ++i) ASSERT_NEAR(a[i], b[i], 1e-12);
    for (size_t i = 0; i < sa.size(); ++i) ASSERT_NEAR(sa[i], sb[i], 1e-12);
  }
}

TEST(FieldEval, NonFinitePositionsStayInsideThePlanes) {
  const FieldConfig c = SmallConfig();
  const FieldLayout L = FieldLayout::Make(c);
  const std::vector<float> P = RandomParams<float>(c, L, 2);
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  const std::vector<float> means = {nan, 0, 0, inf, -inf, 1e30f, 0, 0, 0};
  ThreadPool pool(2);
  FieldWorkspace ws;
  std::vector<float> dx(9), dsh(3 * 48), gp(L.total, 0), gm(9, 0), g_dx(9, 1), g_dsh(3 * 48, 1);
  FieldForward<float>(L, P.data(), TestQuery(0), means.data(), nullptr, 3, dx.data(), dsh.data(), pool, ws);
  for (float v : dx) EXPECT_TRUE(std::isfinite(v));
  FieldBackward<float>(L, P.data(), TestQuery(0), means.data(), 3, g_dx.data(), g_dsh.data(), gp.data(), gm.data(),
                       pool, ws);
  for (float v : gp) ASSERT_TRUE(std::isfinite(v));
}

TEST(FieldEval, CreateRejectsBadInput) {
  FieldAabb flat = TestAabb();
  flat.max[2] = flat.min[2];
  EXPECT_FALSE(DeformationField::Create(SmallConfig(), flat, {0, 1}, 1).ok());
  FieldAabb nan = TestAabb();
  nan.min[0] = std::nan("");
  EXPECT_FALSE(DeformationField::Create(SmallConfig(), nan, {0, 1}, 1).ok());
  EXPECT_FALSE(DeformationField::Create(SmallConfig(), TestAabb(), {10, 1}, 1).ok());
  FieldConfig c = SmallConfig();
  c.time_resolution = 1;
  EXPECT_FALSE(DeformationField::Create(c, TestAabb(), {0, 1}, 1).ok());
  c = SmallConfig();
  c.multires = {};
  EXPECT_FALSE(DeformationField::Create(c, TestAabb(), {0, 1}, 1).ok());
  c = SmallConfig();
  c.channels = 0;
  EXPECT_FALSE(DeformationField::Create(c, TestAabb(), {0, 1}, 1).ok());
  EXPECT_FALSE(DeformationField::FromParams(SmallConfig(), TestAabb(), {0, 1}, std::vector<float>(3, 0.f)).ok());
}

TEST(FieldEval, SpecParameterCount) {
  const FieldLayout L = FieldLayout::Make(FieldConfig{});
  EXPECT_EQ(L.grid_size, 35'727'360u);  // spec 3.1
  // Trunk + Δposition + ΔSH heads (spec 3.2: 8 256 + 4 355 + 7 280; no semantic head).
  EXPECT_EQ(L.total - L.grid_size, 8256u + 4355u + 7280u);
  EXPECT_EQ(L.planes[0].size(32) * 3 + L.planes[2].size(32) * 3, 546'816u);  // level 1
}

}  // namespace
}  // namespace streetsim::field
