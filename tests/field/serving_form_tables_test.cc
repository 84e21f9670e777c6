// The serving form's compact tables (scene/field/serving_form_tables.h) on control points made up
// here: what each part keeps exactly, what it approximates, and what a moving Gaussian costs.
#include <cmath>
#include <random>

#include "gtest/gtest.h"
#include "scene/field/serving_form_tables.h"

namespace streetsim::field {
namespace {

constexpr int kM = 25;  // control points: the spec's time grid
constexpr uint32_t kBit(FormGroup g) { return 1u << static_cast<int>(g); }
constexpr uint32_t kS3Groups = kBit(FormGroup::kPosition) | kBit(FormGroup::kColour) | kBit(FormGroup::kShBands);
constexpr uint32_t kAllGroups = (1u << kFormGroups) - 1;

int Channels(uint32_t groups) {
  int c = 0;
  for (int g = 0; g < kFormGroups; ++g) c += (groups & (1u << g)) ? kFormGroupChannels[g] : 0;
  return c;
}

// Evaluates control point m exactly (weights 1, 0) into a store of `rows` Gaussians.
GaussianStore At(const FormTables& t, int m, size_t rows, ThreadPool& pool) {
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(rows);
  std::vector<uint32_t> index(rows);
  for (size_t r = 0; r < rows; ++r) index[r] = static_cast<uint32_t>(r);
  // The last control point is the second tap of the last segment.
  const bool last = m == kM - 1;
  const float w[2] = {last ? 0.0f : 1.0f, last ? 1.0f : 0.0f};
  const float line = static_cast<float>(m) / (kM - 1);  // w[0] * k + w[1] * (k + 1) over M - 1
  t.Evaluate<2>(last ? m - 1 : m, w, line, index.data(), &g, pool);
  return g;
}

TEST(FormTables, ADrivingGaussianKeepsMillimetresOverTwentyMetres) {
  ThreadPool pool(1);
  const int C = Channels(kS3Groups);
  std::vector<float> coef(kM * C, 0.0f);
  for (int m = 0; m < kM; ++m) {
    // 20 m along x at a steady speed, a 30 cm lane change in y, 5 cm of bounce in z.
    coef[m * C + 0] = 100.0f + 20.0f * m / (kM - 1);
    coef[m * C + 1] = -50.0f + 0.3f * static_cast<float>(std::tanh((m - 12) / 3.0));
    coef[m * C + 2] = 2.0f + 0.05f * static_cast<float>(std::sin(m));
  }
  const FormTables t = FormTables::Quantise(coef, 1, kM, kS3Groups, 1, pool);
  for (int m = 0; m < kM; ++m) {
    const GaussianStore g = At(t, m, 1, pool);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(g.means[c], coef[m * C + c], 2e-3) << "control point " << m << " axis " << c;
  }
}

TEST(FormTables, ARankOneChangeOfAppearanceIsKeptAndAHigherRankNeedsMoreTerms) {
  ThreadPool pool(2);
  const int C = Channels(kS3Groups);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-1, 1);
  // Row 0: time-mean + a(t) d (rank 1). Row 1: + a(t) d + b(t) e (rank 2). Row 2: no change.
  std::vector<float> mean(3 * 48), d(48), e(48);
  for (float& x : mean) x = u(rng);
  for (float& x : d) x = 0.2f * u(rng);
  for (float& x : e) x = 0.2f * u(rng);
  std::vector<float> coef(3 * kM * C, 0.0f);
  for (int r = 0; r < 3; ++r) {
    for (int m = 0; m < kM; ++m) {
      const float a = std::sin(0.4f * m), b = std::cos(0.9f * m);
      for (int c = 0; c < 48; ++c) {
        float v = mean[r * 48 + c];
        if (r < 2) v += a * d[c];
        if (r == 1) v += b * e[c];
        coef[(r * kM + m) * C + 3 + c] = v;
      }
    }
  }
  auto worst = [&](const FormTables& t, int row) {
    float err = 0;
    for (int m = 0; m < kM; ++m) {
      const GaussianStore g = At(t, m, 3, pool);
      for (int c = 0; c < 48; ++c) err = std::max(err, std::abs(g.sh[row * 48 + c] - coef[(row * kM + m) * C + 3 + c]));
    }
    return err;
  };
  const FormTables rank1 = FormTables::Quantise(coef, 3, kM, kS3Groups, 1, pool);
  const FormTables rank2 = FormTables::Quantise(coef, 3, kM, kS3Groups, 2, pool);
  EXPECT_EQ(rank1.appearance_rank(), 1);
  EXPECT_LT(worst(rank1, 0), 0.02f) << "rank 1 keeps a rank-1 change (int8 floor)";
  EXPECT_LT(worst(rank1, 2), 0.01f) << "no change: the time-mean alone";
  EXPECT_GT(worst(rank1, 1), 0.05f) << "a rank-2 change is beyond rank 1";
  EXPECT_LT(worst(rank2, 1), 0.02f) << "and within rank 2";
}

TEST(FormTables, TheExtendedFieldsGroupsAreKeptAtFullRank) {
  ThreadPool pool(1);
  const int C = Channels(kAllGroups);
  std::mt19937 rng(8);
  std::uniform_real_distribution<float> u(-1, 1);
  std::vector<float> coef(kM * C);
  for (float& x : coef) x = u(rng);  // every channel changes independently
  const FormTables t = FormTables::Quantise(coef, 1, kM, kAllGroups, 1, pool);
  // Table order: position 0-2, colour 3-5, log-scale 6-8, rotation 9-12, opacity 13, bands 14-58.
  for (int m = 0; m < kM; ++m) {
    const GaussianStore g = At(t, m, 1, pool);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(g.log_scales[c], coef[m * C + 6 + c], 0.03f) << m;
    for (int c = 0; c < 4; ++c) EXPECT_NEAR(g.rotations[c], coef[m * C + 9 + c], 0.03f) << m;
    EXPECT_NEAR(g.opacity_logits[0], coef[m * C + 13], 0.02f) << m;
  }
}

TEST(FormTables, AMovingGaussianOfS3GaussiansFieldCostsAtMost250Bytes) {
  ThreadPool pool(2);
  const size_t rows = 1000;
  const int C = Channels(kS3Groups);
  std::vector<float> coef(rows * kM * C, 0.5f);
  const FormTables t = FormTables::Quantise(coef, rows, kM, kS3Groups, kDefaultAppearanceRank, pool);
  // + 4 B for the row index the form keeps beside the tables.
  EXPECT_LE(t.bytes() / rows + sizeof(uint32_t), 250u);
}

TEST(Bf16, RoundsAndBoundsFromAbove) {
  for (float x : {0.0f, 1e-6f, 0.3f, 1.0f, 3.14159f, 1234.5f}) {
    EXPECT_NEAR(FromBf16(ToBf16(x)), x, x / 256) << x;
    EXPECT_GE(FromBf16(Bf16AtLeast(x)), x) << x;
    EXPECT_LE(FromBf16(Bf16AtLeast(x)), x * (1 + 1.0f / 128) + 1e-30f) << x;
  }
}

}  // namespace
}  // namespace streetsim::field
