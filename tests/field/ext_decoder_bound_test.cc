// The bound on the extended decoder's Δlog-scale (scene/field/extended/extended_config.h): the
// deformed log-scales stay within B of the canonical ones however large the head's output, the
// backward passes dL/d(log s) through B tanh(Δ / B), and the serving field applies the same bound.
#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/extended/extended_serving.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

constexpr size_t kN = 96;
constexpr float kBound = 0.5f;

struct Canonical {
  std::vector<float> means, sh, log_scales, rotations, opacity;
  ExtCanonicalView view() const {
    return {kN, means.data(), sh.data(), log_scales.data(), rotations.data(), opacity.data()};
  }
};

Canonical MakeCanonical() {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<float> u(0.0f, 1.0f);
  const FieldAabb a = testing::TestAabb();
  Canonical c;
  for (size_t i = 0; i < kN; ++i) {
    for (int k = 0; k < 3; ++k) c.means.push_back(a.min[k] + (a.max[k] - a.min[k]) * u(rng));
    for (int k = 0; k < 3; ++k) c.log_scales.push_back(-4.0f + 2.0f * u(rng));
    c.rotations.insert(c.rotations.end(), {1.0f, 0.1f * u(rng), 0.0f, 0.0f});
    c.opacity.push_back(u(rng) - 0.5f);
    for (int k = 0; k < kShOutputs; ++k) c.sh.push_back(0.2f * (u(rng) - 0.5f));
  }
  return c;
}

// The decoder alone on a small field; its Δlog-scale head (initialised to output 0) given large
// random weights so that its output leaves the bound.
ExtendedField MakeDecoderField(float bound) {
  absl::StatusOr<DeformationField> base =
      DeformationField::Create(testing::SmallConfig(), testing::TestAabb(), {1000, 2000000}, 3);
  EXPECT_TRUE(base.ok());
  ExtendedFieldConfig c = *ExtendedFieldConfig::WithModules("decoder");
  c.decoder_max_dlog_scale = bound;
  absl::StatusOr<ExtendedField> f = ExtendedField::Create(std::move(*base), c, 3);
  EXPECT_TRUE(f.ok()) << f.status();
  const nn::LinearSpec& s2 = f->layout().scale2;
  std::mt19937_64 rng(7);
  std::normal_distribution<float> w(0.0f, 30.0f);
  for (size_t i = 0; i < size_t(s2.in) * s2.out; ++i) f->mutable_params()[s2.w_offset + i] = w(rng);
  for (int i = 0; i < s2.out && s2.bias; ++i) f->mutable_params()[s2.b_offset + i] = 0.1f * w(rng);
  return std::move(*f);
}

ExtendedField WithBound(const ExtendedField& f, float bound) {
  ExtendedFieldConfig c = f.config();
  c.decoder_max_dlog_scale = bound;
  absl::StatusOr<ExtendedField> g = ExtendedField::FromParams(f.base(), c, f.params());
  EXPECT_TRUE(g.ok()) << g.status();
  return std::move(*g);
}

// The canonical scene, the decoder field with the bound and without it, both deformed at one time.
struct BoundPair {
  Canonical c = MakeCanonical();
  ExtendedField bounded = MakeDecoderField(kBound), raw = WithBound(bounded, 0.0f);
  ThreadPool pool{2};
  ExtWorkspace ws;
  ExtDeformedScene db, d0;
  bool deformed = false;  // both passes succeeded (tests assert it before reading db / d0)
  explicit BoundPair(double time_coord) {
    ExtPass pass;
    pass.time_coord = time_coord;
    deformed = DeformSceneExt(bounded, pass, c.view(), pool, ws, &db).ok() &&
               DeformSceneExt(raw, pass, c.view(), pool, ws, &d0).ok();
  }
};

TEST(DecoderBound, DeformedLogScalesStayWithinTheBound) {
  BoundPair p(0.3);
  ASSERT_TRUE(p.deformed);
  const Canonical& c = p.c;
  const ExtDeformedScene &db = p.db, &d0 = p.d0;
  float raw_max = 0;
  for (size_t i = 0; i < kN * 3; ++i) {
    raw_max = std::max(raw_max, std::abs(d0.dscale[i]));
    EXPECT_NEAR(db.dscale[i], kBound * std::tanh(d0.dscale[i] / kBound), 1e-6f) << i;
    EXPECT_LE(std::abs(db.log_scales[i] - c.log_scales[i]), kBound * (1 + 1e-6f)) << i;
    EXPECT_EQ(db.log_scales[i], c.log_scales[i] + db.dscale[i]);
    EXPECT_EQ(d0.log_scales[i], c.log_scales[i] + d0.dscale[i]);  // B = 0: as before, unbounded
  }
  EXPECT_GT(raw_max, 4 * kBound);  // the head's output does leave the bound
  // The rest of the deformation does not depend on the bound.
  EXPECT_EQ(db.means, d0.means);
  EXPECT_EQ(db.rotations, d0.rotations);
  EXPECT_EQ(db.opacity_logits, d0.opacity_logits);
}

TEST(DecoderBound, BackwardChainsTheBound) {
  // dL/dθ with the bound and rendered gradient G on the log-scales = dL/dθ without it and
  // gradient G (1 - (Δ_bounded / B)²): the bound's whole effect on the backward is that factor.
  BoundPair p(-0.4);
  ASSERT_TRUE(p.deformed);
  const Canonical& c = p.c;
  const ExtendedField &bounded = p.bounded, &raw = p.raw;
  ThreadPool& pool = p.pool;
  ExtWorkspace& ws = p.ws;
  const ExtDeformedScene &db = p.db, &d0 = p.d0;
  std::mt19937_64 rng(5);
  std::normal_distribution<float> g(0.0f, 1.0f);
  GaussianGrads gb;
  gb.means.assign(kN * 3, 0.0f);
  gb.sh.assign(kN * kShOutputs, 0.0f);
  gb.rotations.assign(kN * 4, 0.0f);
  gb.opacity_logits.assign(kN, 0.0f);
  for (size_t i = 0; i < kN * 3; ++i) gb.log_scales.push_back(g(rng));
  for (float& v : gb.opacity_logits) v = g(rng);
  GaussianGrads g0 = gb;
  size_t damped = 0;
  for (size_t i = 0; i < kN * 3; ++i) {
    const float u = db.dscale[i] / kBound;
    g0.log_scales[i] *= 1.0f - u * u;
    damped += std::abs(u) > 0.9f;
  }
  EXPECT_GT(damped, 0u);  // some Gaussians sit in the bound's flat part
  FieldHyper h;
  std::vector<float> base_b, ext_b, base_0, ext_0;
  ASSERT_TRUE(DeformBackwardExt(bounded, c.view(), db, 3, h, 0.0, pool, ws, &gb, &base_b, &ext_b).ok());
  ASSERT_TRUE(DeformBackwardExt(raw, c.view(), d0, 3, h, 0.0, pool, ws, &g0, &base_0, &ext_0).ok());
  ASSERT_EQ(ext_b.size(), ext_0.size());
  double num = 0, den = 0;
  for (size_t i = 0; i < ext_b.size(); ++i) num += double(ext_b[i] - ext_0[i]) * (ext_b[i] - ext_0[i]);
  for (float v : ext_0) den += double(v) * v;
  EXPECT_GT(den, 0);
  EXPECT_LT(std::sqrt(num / den), 1e-6);
  num = den = 0;
  for (size_t i = 0; i < base_b.size(); ++i) num += double(base_b[i] - base_0[i]) * (base_b[i] - base_0[i]);
  for (float v : base_0) den += double(v) * v;
  EXPECT_LT(std::sqrt(num / std::max(den, 1e-30)), 1e-6);
}

TEST(DecoderBound, ServingAppliesTheSameBound) {
  const Canonical c = MakeCanonical();
  const ExtendedField bounded = MakeDecoderField(kBound);
  GaussianStore store;
  store.sh_degree = 3;
  store.means = c.means;
  store.log_scales = c.log_scales;
  store.rotations = c.rotations;
  store.opacity_logits = c.opacity;
  store.sh = c.sh;
  ThreadPool pool(2);
  const int64_t t_us = 700000;
  absl::StatusOr<GaussianStore> trained = ExtDeformedStore(bounded, store, t_us, pool);
  ASSERT_TRUE(trained.ok()) << trained.status();
  StaticSkipOptions none;
  none.enabled = false;  // every Gaussian evaluated at every timestamp
  absl::StatusOr<std::unique_ptr<ExtServingField>> served = ExtServingField::Create(bounded, store, none, pool);
  ASSERT_TRUE(served.ok()) << served.status();
  absl::StatusOr<const GaussianStore*> at = (*served)->At(t_us, pool);
  ASSERT_TRUE(at.ok()) << at.status();
  for (size_t i = 0; i < kN * 3; ++i) {
    EXPECT_NEAR((*at)->log_scales[i], trained->log_scales[i], 1e-5f) << i;
    EXPECT_LE(std::abs((*at)->log_scales[i] - c.log_scales[i]), kBound * (1 + 1e-6f)) << i;
  }
}

}  // namespace
}  // namespace streetsim::field
