// The serving form written into an engine's planes (FormTables::EvaluateIntoPlanes, what
// field::HostPlanesWriter writes into the cpu engine's copy of a scene) against the same form
// written into a store (Evaluate, the host path): the same values in every modelled channel of
// every moving row, nothing else touched, whether the rows come in whole cache-line runs or not,
// with the LiDAR's geometry written in the same pass; and a geometry-only evaluation (the LiDAR's)
// that leaves the appearance alone.
#include <cmath>
#include <cstdint>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "scene/field/serving_form_tables.h"

namespace streetsim::field {
namespace {

constexpr int kM = 25;
constexpr uint32_t kBit(FormGroup g) { return 1u << static_cast<int>(g); }
constexpr uint32_t kS3Groups = kBit(FormGroup::kPosition) | kBit(FormGroup::kColour) | kBit(FormGroup::kShBands);
constexpr uint32_t kAllGroups = (1u << kFormGroups) - 1;
constexpr float kUntouched = -7.25f;

int Channels(uint32_t groups) {
  int c = 0;
  for (int g = 0; g < kFormGroups; ++g) c += (groups & (1u << g)) ? kFormGroupChannels[g] : 0;
  return c;
}

// Planes of n Gaussians at SH degree 3 laid out as the cpu engine lays them out (SH 64-byte
// aligned, planes a multiple of 16 apart), every value kUntouched.
struct OwnedPlanes {
  std::vector<std::vector<float>> scalar;  // mean x3, log-scale x3, rotation x4, opacity
  std::vector<float> sh_storage;
  ScenePlanes planes;

  explicit OwnedPlanes(size_t n) : scalar(11, std::vector<float>(n, kUntouched)) {
    planes.n = n;
    planes.sh_degree = 3;
    for (int c = 0; c < 3; ++c) planes.mean[c] = scalar[c].data(), planes.log_scale[c] = scalar[3 + c].data();
    for (int c = 0; c < 4; ++c) planes.rotation[c] = scalar[6 + c].data();
    planes.opacity_logit = scalar[10].data();
    planes.sh_plane = (n + 15) / 16 * 16;
    sh_storage.assign(48 * planes.sh_plane + 16, kUntouched);
    float* p = sh_storage.data();
    while (reinterpret_cast<uintptr_t>(p) % 64 != 0) ++p;
    planes.sh = p;
  }
  float Sh(size_t i, int kc) const { return planes.sh[kc * planes.sh_plane + i]; }
};

GaussianStore UntouchedStore(size_t n) {
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n);
  for (auto* v : {&g.means, &g.log_scales, &g.rotations, &g.opacity_logits, &g.sh}) v->assign(v->size(), kUntouched);
  return g;
}

// A run of consecutive rows that starts off a cache line (3..502), then every other row, so that
// both the whole-line path and the row-at-a-time path write.
std::vector<uint32_t> MovingRows() {
  std::vector<uint32_t> rows;
  for (uint32_t i = 3; i < 503; ++i) rows.push_back(i);
  for (uint32_t i = 600; i < 1600; i += 2) rows.push_back(i);
  return rows;
}
constexpr size_t kGaussians = 1610;

FormTables RandomTables(uint32_t groups, int rank, size_t rows, uint32_t seed, ThreadPool& pool) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-1, 1);
  const int C = Channels(groups);
  std::vector<float> coef(rows * kM * C);
  for (float& x : coef) x = u(rng);
  for (size_t r = 0; r < rows; ++r) {
    for (int m = 0; m < kM; ++m) coef[(r * kM + m) * C] += 30.0f + 0.5f * m;  // driving along x
  }
  return FormTables::Quantise(coef, rows, kM, groups, rank, pool);
}

void ExpectClose(float a, float b, const std::string& what) {
  EXPECT_NEAR(a, b, 1e-5f * std::max(1.0f, std::abs(b))) << what;
}

template <int kTaps>
void ExpectPlanesHoldTheStore(uint32_t groups, int rank) {
  ThreadPool pool(2);
  const std::vector<uint32_t> rows = MovingRows();
  const FormTables t = RandomTables(groups, rank, rows.size(), 5, pool);
  const float w2[2] = {0.3f, 0.7f}, w4[4] = {0.1f, 0.5f, 0.3f, 0.1f};
  const float* w = kTaps == 2 ? w2 : w4;
  const int k = 7;
  float line = 0;
  for (int j = 0; j < kTaps; ++j) line += w[j] * (k + j);
  line /= kM - 1;

  GaussianStore store = UntouchedStore(kGaussians);
  t.Evaluate<kTaps>(k, w, line, rows.data(), &store, pool);
  OwnedPlanes planes(kGaussians);
  GaussianStore geometry = UntouchedStore(kGaussians);  // the LiDAR's copy, written in the same pass
  ASSERT_TRUE(t.EvaluateIntoPlanes<kTaps>(k, w, line, rows.data(), planes.planes, pool, &geometry));

  const std::string tag = "taps " + std::to_string(kTaps) + " groups " + std::to_string(groups);
  int moved = 0;
  for (size_t i = 0; i < kGaussians; ++i) {
    const std::string at = tag + " Gaussian " + std::to_string(i);
    for (int c = 0; c < 3; ++c) {
      ExpectClose(planes.planes.mean[c][i], store.means[i * 3 + c], at + " mean");
      ExpectClose(planes.planes.log_scale[c][i], store.log_scales[i * 3 + c], at + " log-scale");
    }
    for (int c = 0; c < 4; ++c) ExpectClose(planes.planes.rotation[c][i], store.rotations[i * 4 + c], at + " rotation");
    ExpectClose(planes.planes.opacity_logit[i], store.opacity_logits[i], at + " opacity");
    for (int kc = 0; kc < 48; ++kc) {
      ExpectClose(planes.Sh(i, kc), store.sh[i * 48 + kc], at + " SH " + std::to_string(kc));
      EXPECT_EQ(geometry.sh[i * 48 + kc], kUntouched) << at << ": the appearance is not the LiDAR's";
    }
    for (int c = 0; c < 3; ++c) {
      EXPECT_EQ(geometry.means[i * 3 + c], store.means[i * 3 + c]) << at;
      EXPECT_EQ(geometry.log_scales[i * 3 + c], store.log_scales[i * 3 + c]) << at;
    }
    for (int c = 0; c < 4; ++c) EXPECT_EQ(geometry.rotations[i * 4 + c], store.rotations[i * 4 + c]) << at;
    EXPECT_EQ(geometry.opacity_logits[i], store.opacity_logits[i]) << at;
    moved += store.means[i * 3] != kUntouched;
    if (::testing::Test::HasFailure()) return;
  }
  EXPECT_EQ(moved, static_cast<int>(rows.size())) << tag;  // and every other row kept its value
}

TEST(FormPlanes, S3GaussiansFormWritesThePlanesAsTheStore) {
  ExpectPlanesHoldTheStore<2>(kS3Groups, 1);
  ExpectPlanesHoldTheStore<4>(kS3Groups, 1);
}

TEST(FormPlanes, EveryGroupAtAHigherRankWritesThePlanesAsTheStore) {
  ExpectPlanesHoldTheStore<2>(kS3Groups, 3);
  ExpectPlanesHoldTheStore<2>(kAllGroups, 2);
  ExpectPlanesHoldTheStore<4>(kAllGroups, 1);
}

TEST(FormPlanes, AZeroRotationIsReported) {
  ThreadPool pool(1);
  const int C = Channels(kAllGroups);
  std::vector<float> coef(2 * kM * C, 0.5f);
  // Row 1's rotation (table channels 9-12) is zero at every control point.
  for (int m = 0; m < kM; ++m)
    for (int c = 9; c < 13; ++c) coef[(kM + m) * C + c] = 0.0f;
  const FormTables t = FormTables::Quantise(coef, 2, kM, kAllGroups, 1, pool);
  const uint32_t rows[2] = {0, 1};
  const float w[2] = {0.5f, 0.5f};
  OwnedPlanes planes(2);
  EXPECT_FALSE(t.EvaluateIntoPlanes<2>(3, w, 3.5f / (kM - 1), rows, planes.planes, pool));
}

TEST(FormPlanes, AGeometryOnlyEvaluationLeavesTheAppearanceAlone) {
  ThreadPool pool(2);
  const std::vector<uint32_t> rows = MovingRows();
  const FormTables t = RandomTables(kS3Groups, 1, rows.size(), 9, pool);
  const float w[2] = {0.25f, 0.75f};
  const float line = (0.25f * 4 + 0.75f * 5) / (kM - 1);
  GaussianStore full = UntouchedStore(kGaussians), geometry = UntouchedStore(kGaussians);
  t.Evaluate<2>(4, w, line, rows.data(), &full, pool);
  t.Evaluate<2>(4, w, line, rows.data(), &geometry, pool, ~(kBit(FormGroup::kColour) | kBit(FormGroup::kShBands)));
  EXPECT_EQ(geometry.means, full.means);
  for (float v : geometry.sh) ASSERT_EQ(v, kUntouched);
  EXPECT_NE(full.sh, geometry.sh);
}

}  // namespace
}  // namespace streetsim::field
