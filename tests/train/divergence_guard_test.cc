// The divergence guard (scene/train/divergence_guard.h) on loss sequences: a run that settles is
// fine, one that climbs is suspicious and then diverged, a non-finite loss is diverged at once,
// and a re-baseline (the fine stage's start, an opacity reset) forgives the jump it causes.
// The rollback it drives is tested through the CLI (cli_train_test.cc).
#include "scene/train/divergence_guard.h"

#include <cmath>
#include <limits>

#include "gtest/gtest.h"

namespace streetsim::train {
namespace {

using V = DivergenceGuard::Verdict;

TEST(DivergenceGuard, ASettlingLossIsFine) {
  DivergenceGuard g;
  for (int it = 1; it <= 2000; ++it) {
    // Noisy, decreasing, with the LiDAR term on every other iteration.
    const double loss = 0.2 + 0.3 * std::exp(-it / 300.0) + (it % 2 ? 0.05 : 0) + 0.02 * std::sin(it * 0.7);
    ASSERT_EQ(g.Observe(it, loss, 20), V::kFine) << it;
  }
}

TEST(DivergenceGuard, AClimbingLossIsSuspiciousThenDiverged) {
  DivergenceGuard g;
  int64_t it = 1;
  for (; it <= 500; ++it) ASSERT_EQ(g.Observe(it, 0.2, 20), V::kFine);
  // The climb of issue 34's moving-ego run: 0.2 to 2.2 over a few hundred iterations.
  int64_t suspicious_at = 0, diverged_at = 0;
  for (; it <= 1500 && diverged_at == 0; ++it) {
    const double loss = 0.2 + 2.0 * std::min(1.0, (it - 500) / 400.0);
    const V v = g.Observe(it, loss, 20);
    if (v == V::kSuspicious && suspicious_at == 0) suspicious_at = it;
    if (v == V::kDiverged) diverged_at = it;
  }
  ASSERT_GT(suspicious_at, 500);
  ASSERT_GT(diverged_at, suspicious_at);
  EXPECT_LT(diverged_at, 900) << "diverged long after the loss tripled";
  EXPECT_GT(g.mean(), 3 * g.best());
}

// A saturating photometric loss: the loss only doubles, the PSNR falls 7 dB (the KITTI run of
// tests/train/cli_train_test.cc with absurd pose rates).
TEST(DivergenceGuard, APsnrCollapseIsDivergedWhenTheLossSaturates) {
  DivergenceGuard g;
  int64_t it = 1;
  for (; it <= 500; ++it) ASSERT_EQ(g.Observe(it, 0.15, 16.8), V::kFine);
  V worst = V::kFine;
  for (; it <= 900; ++it) worst = std::max(worst, g.Observe(it, 0.4, 9.4));
  EXPECT_EQ(worst, V::kDiverged);
  EXPECT_LT(g.mean(), 3 * g.best()) << "the loss alone would not have said it";
  EXPECT_NE(g.why().find("dB below its best"), std::string::npos) << g.why();
}

TEST(DivergenceGuard, NonFiniteLossIsDivergedAtOnce) {
  DivergenceGuard g;
  EXPECT_EQ(g.Observe(1, 0.3, 20), V::kFine);
  EXPECT_EQ(g.Observe(2, std::numeric_limits<double>::quiet_NaN(), 20), V::kDiverged);
  EXPECT_EQ(g.Observe(3, std::numeric_limits<double>::infinity(), 20), V::kDiverged);
}

TEST(DivergenceGuard, ARebaselineForgivesAnIntendedJump) {
  DivergenceGuard a, b;
  for (int it = 1; it <= 600; ++it) {
    a.Observe(it, 0.1, 20);
    b.Observe(it, 0.1, 20);
  }
  b.Rebaseline(601);  // an opacity reset: every opacity at 0.01, the loss jumps and recovers
  V worst_a = V::kFine, worst_b = V::kFine;
  for (int it = 601; it <= 1400; ++it) {
    const double loss = 0.1 + 0.6 * std::exp(-(it - 601) / 150.0);
    worst_a = std::max(worst_a, a.Observe(it, loss, 20));
    worst_b = std::max(worst_b, b.Observe(it, loss, 20));
  }
  EXPECT_EQ(worst_a, V::kDiverged) << "the same jump without the baseline is a divergence";
  EXPECT_NE(worst_b, V::kDiverged);
}

}  // namespace
}  // namespace streetsim::train
