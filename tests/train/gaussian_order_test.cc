// The fine stage keeps the Gaussians in the field's Morton order (DynamicStage::OrderGaussians,
// train::PermuteRows): every per-Gaussian array moves with its row, bad orders are refused, and
// after ordering the rows are in Morton order of their canonical means.
#include <cmath>
#include <numeric>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "scene/field/spatial_order.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/train_state.h"
#include "tests/train/field_stage_fixtures.h"

namespace streetsim::train {
namespace {

// n Gaussians scattered in a 40 x 20 x 4 m box; every per-Gaussian value of row i encodes i, so
// that a test can tell which row a value came from.
TrainState TaggedState(size_t n, uint64_t seed) {
  GaussianStore g = fixtures::ScatteredGaussians(n, seed);
  for (size_t i = 0; i < n; ++i) {
    const float fi = static_cast<float>(i);
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = -3.0f - 0.001f * fi;
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = k == 0 ? 1.0f : k == 3 ? 0.001f * fi : 0.0f;
    g.opacity_logits[i] = 0.01f * fi;
    for (int k = 0; k < 48; ++k) g.sh[i * 48 + k] = fi + 0.001f * static_cast<float>(k);
  }
  TrainState st = TrainState::Init(g, 10.0, 1, 1);
  for (size_t i = 0; i < n; ++i) {
    const float tag = static_cast<float>(i);
    st.adam_m.means[i * 3 + 1] = tag;
    st.adam_v.sh[i * 48 + 47] = tag;
    st.adam_m.opacity_logits[i] = tag;
    st.adam_v.rotations[i * 4 + 2] = tag;
    st.grad_accum[i] = tag;
    st.denom[i] = tag + 1;
    st.max_radii[i] = tag + 2;
  }
  st.reflectance_logit.resize(n);
  st.reflectance_m.resize(n);
  st.reflectance_v.resize(n);
  for (size_t i = 0; i < n; ++i) {
    st.reflectance_logit[i] = static_cast<float>(i);
    st.reflectance_m[i] = static_cast<float>(i) + 0.5f;
    st.reflectance_v[i] = static_cast<float>(i) + 0.25f;
  }
  return st;
}

TEST(GaussianOrder, PermuteRowsMovesEveryArrayWithItsRow) {
  const size_t n = 57;
  const TrainState before = TaggedState(n, 3);
  TrainState st = before;
  std::vector<uint32_t> order(n);
  std::iota(order.begin(), order.end(), 0u);
  std::shuffle(order.begin(), order.end(), std::mt19937(11));
  ASSERT_TRUE(PermuteRows(&st, order).ok());
  ASSERT_EQ(st.size(), n);
  for (size_t r = 0; r < n; ++r) {
    const size_t i = order[r];
    for (int k = 0; k < 3; ++k) {
      EXPECT_EQ(st.params.means[r * 3 + k], before.params.means[i * 3 + k]);
      EXPECT_EQ(st.params.log_scales[r * 3 + k], before.params.log_scales[i * 3 + k]);
    }
    for (int k = 0; k < 4; ++k) EXPECT_EQ(st.params.rotations[r * 4 + k], before.params.rotations[i * 4 + k]);
    for (int k = 0; k < 48; ++k) EXPECT_EQ(st.params.sh[r * 48 + k], before.params.sh[i * 48 + k]);
    EXPECT_EQ(st.params.opacity_logits[r], before.params.opacity_logits[i]);
    const float tag = static_cast<float>(i);
    EXPECT_EQ(st.adam_m.means[r * 3 + 1], tag);
    EXPECT_EQ(st.adam_v.sh[r * 48 + 47], tag);
    EXPECT_EQ(st.adam_m.opacity_logits[r], tag);
    EXPECT_EQ(st.adam_v.rotations[r * 4 + 2], tag);
    EXPECT_EQ(st.grad_accum[r], tag);
    EXPECT_EQ(st.denom[r], tag + 1);
    EXPECT_EQ(st.max_radii[r], tag + 2);
    EXPECT_EQ(st.reflectance_logit[r], tag);
    EXPECT_EQ(st.reflectance_m[r], tag + 0.5f);
    EXPECT_EQ(st.reflectance_v[r], tag + 0.25f);
  }
  // Everything that is not per Gaussian stays.
  EXPECT_EQ(st.iteration, before.iteration);
  EXPECT_EQ(st.adam_step, before.adam_step);
}

TEST(GaussianOrder, PermuteRowsRefusesWhatIsNotAPermutation) {
  const TrainState before = TaggedState(6, 4);
  for (const std::vector<uint32_t>& bad : std::vector<std::vector<uint32_t>>{
           {0, 1, 2, 3, 4},           // too short
           {0, 1, 2, 3, 4, 5, 0},     // too long
           {0, 1, 2, 3, 4, 4},        // a repeat
           {0, 1, 2, 3, 4, 6},        // out of range
       }) {
    TrainState st = before;
    EXPECT_FALSE(PermuteRows(&st, bad).ok());
    EXPECT_EQ(st.params.means, before.params.means);  // untouched
    EXPECT_EQ(st.adam_m.means, before.adam_m.means);
  }
}

TEST(GaussianOrder, FineStageOrdersTheGaussiansAlongTheFieldsMortonCurve) {
  const size_t n = 3000;
  TrainState st = TaggedState(n, 5);
  FieldOptions options = fixtures::TinyFieldOptions(4);
  absl::StatusOr<std::unique_ptr<DynamicStage>> stage = DynamicStage::Begin(&st, options, {0, 1'000'000});
  ASSERT_TRUE(stage.ok()) << stage.status();
  for (size_t i = 0; i < n; ++i) st.grad_accum[i] = static_cast<float>(i);  // Begin restarted the statistics
  ThreadPool pool(2);
  // The trainer's own order (random here) is not the Morton order.
  std::vector<uint32_t> order = field::SpatialOrder((*stage)->field().aabb(), st.params.means.data(), n, nullptr, pool);
  size_t in_place = 0;
  for (size_t r = 0; r < n; ++r) in_place += order[r] == r;
  EXPECT_LT(in_place, n / 10);

  const TrainState before = st;
  ASSERT_TRUE((*stage)->OrderGaussians(&st, pool).ok());
  order = field::SpatialOrder((*stage)->field().aabb(), st.params.means.data(), n, nullptr, pool);
  for (size_t r = 0; r < n; ++r) ASSERT_EQ(order[r], r) << "row " << r << " is not in Morton order";
  // The same Gaussians, each with its own parameters and state (the tag in its SH).
  std::vector<int> seen(n, 0);
  for (size_t r = 0; r < n; ++r) {
    const size_t i = static_cast<size_t>(std::lround(st.params.sh[r * 48]));
    ASSERT_LT(i, n);
    ++seen[i];
    for (int k = 0; k < 3; ++k) EXPECT_EQ(st.params.means[r * 3 + k], before.params.means[i * 3 + k]);
    EXPECT_EQ(st.grad_accum[r], before.grad_accum[i]);
    EXPECT_EQ(st.reflectance_logit[r], before.reflectance_logit[i]);
  }
  for (size_t i = 0; i < n; ++i) EXPECT_EQ(seen[i], 1) << i;
}

}  // namespace
}  // namespace streetsim::train
