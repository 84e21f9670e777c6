// The fine stage's LiDAR motion prior (scene/train/motion_prior.h): assignment, targets, the
// gradient against finite differences, and bad options.
#include "scene/train/motion_prior.h"

#include <cmath>
#include <random>

#include "gtest/gtest.h"

namespace streetsim::train {
namespace {

Eigen::Isometry3d Shift(double x) {
  Eigen::Isometry3d m = Eigen::Isometry3d::Identity();
  m.translation() = Eigen::Vector3d(x, 0, 0);
  return m;
}

// One object seen at t = 0 s, 1 s and 2 s, moving 10 m along x in the first second, then standing.
// Its points: a 1 m patch around (0, 0, 1) at t = 0, the same patch 10 m on at t = 1 s and 2 s.
std::unique_ptr<MotionPrior> Prior(const MotionPriorOptions& o) {
  MotionPrior::Track track;
  track.time_us = {0, 1'000'000, 2'000'000};
  track.motion = {Shift(0), Shift(10), Shift(10)};
  std::vector<Eigen::Vector3f> points;
  std::vector<int> point_track, point_obs;
  for (int obs = 0; obs < 3; ++obs) {
    for (float y = -0.5f; y <= 0.5f; y += 0.1f) {
      for (float z = 0.5f; z <= 1.5f; z += 0.1f) {
        points.emplace_back(obs == 0 ? 0.0f : 10.0f, y, z);
        point_track.push_back(0);
        point_obs.push_back(obs);
      }
    }
  }
  return MotionPrior::FromTracks({track}, points, point_track, point_obs, o);
}

MotionPriorOptions Options() {
  MotionPriorOptions o;
  o.weight = 2.0;
  return o;
}

TEST(MotionPrior, AGaussianOnAnObjectWhereItsTrackEndsFollowsIt) {
  std::unique_ptr<MotionPrior> prior = Prior(Options());
  ThreadPool pool(2);
  // On the object where it stands at the end (scans at 1 s and 2 s), on its first place (smear, not
  // assigned), and off it.
  const std::vector<float> means = {10.1f, 0.0f, 1.0f, 0.05f, 0.2f, 1.0f, 5.0f, 0.0f, 1.0f, 10.0f, 3.0f, 1.0f};
  prior->Assign(means.data(), 4, pool);
  EXPECT_EQ(prior->assigned(), 1u);
  const auto x = [&](size_t i, int64_t t) { return prior->TargetDx(i, t, means.data()); };
  EXPECT_NEAR(x(0, 0).x(), -10.0, 1e-9);  // where the object was before it stopped
  EXPECT_NEAR(x(0, 500'000).x(), -5.0, 1e-9);
  EXPECT_NEAR(x(0, 1'500'000).norm(), 0.0, 1e-9);
  EXPECT_NEAR(x(0, 9'000'000).norm(), 0.0, 1e-9);  // held after the last scan
  EXPECT_NEAR(x(0, -1'000'000).x(), -10.0, 1e-9);  // held before the first scan
  EXPECT_NEAR(x(1, 250'000).norm(), 0.0, 1e-12);     // the smear stays
  EXPECT_NEAR(x(2, 500'000).norm(), 0.0, 1e-12);
  EXPECT_NEAR(x(3, 500'000).norm(), 0.0, 1e-12);
  // Rows change (densification): the assignment follows the means it is given.
  const std::vector<float> moved = {5.0f, 0.0f, 1.0f};
  prior->Assign(moved.data(), 1, pool);
  EXPECT_EQ(prior->assigned(), 0u);
  EXPECT_EQ(prior->n(), 1u);
}

TEST(MotionPrior, WithAllScansTheSmearIsCarriedFromTheLatestScanThatSawTheObjectThere) {
  MotionPriorOptions o = Options();
  o.all_scans = true;
  std::unique_ptr<MotionPrior> prior = Prior(o);
  ThreadPool pool(2);
  // As above: on the object where it stands at the end, on its first place, and off it.
  const std::vector<float> means = {10.1f, 0.0f, 1.0f, 0.05f, 0.2f, 1.0f, 5.0f, 0.0f, 1.0f, 10.0f, 3.0f, 1.0f};
  prior->Assign(means.data(), 4, pool);
  EXPECT_EQ(prior->assigned(), 2u);
  const auto x = [&](size_t i, int64_t t) { return prior->TargetDx(i, t, means.data()); };
  // Where it stands: from the last scan (the scan at 1 s saw it there too, with the same motion).
  EXPECT_NEAR(x(0, 0).x(), -10.0, 1e-9);
  EXPECT_NEAR(x(0, 2'000'000).norm(), 0.0, 1e-9);
  // The smear on its first place (seen there at 0 s only) goes with it and ends on it.
  EXPECT_NEAR(x(1, 0).norm(), 0.0, 1e-9);
  EXPECT_NEAR(x(1, 500'000).x(), 5.0, 1e-9);
  EXPECT_NEAR(x(1, 2'000'000).x(), 10.0, 1e-9);
  EXPECT_NEAR(x(1, 2'000'000).y(), 0.0, 1e-9);
  EXPECT_NEAR(x(2, 500'000).norm(), 0.0, 1e-12);  // off the object
  EXPECT_NEAR(x(3, 500'000).norm(), 0.0, 1e-12);
}

TEST(MotionPrior, GradientMatchesFiniteDifferencesInBothHuberRegimes) {
  std::unique_ptr<MotionPrior> prior = Prior(Options());
  ThreadPool pool(2);
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-0.4f, 0.4f);
  const size_t n = 40;
  std::vector<float> means(n * 3), deformed(n * 3);
  for (size_t i = 0; i < n; ++i) {
    means[i * 3] = (i % 3 == 0 ? 0.0f : 10.0f) + u(rng) * 0.3f;  // a third on the first place: smear
    means[i * 3 + 1] = u(rng);
    means[i * 3 + 2] = 1.0f + u(rng);
    if (i % 5 == 4) means[i * 3 + 1] += 5;  // off the object
    // Δx: near the target for some (quadratic), metres off for others (linear).
    const float off = i % 2 ? 0.1f : 3.0f;
    for (int c = 0; c < 3; ++c) deformed[i * 3 + c] = means[i * 3 + c] + off * u(rng);
  }
  prior->Assign(means.data(), n, pool);
  ASSERT_GT(prior->assigned(), 15u);
  const int64_t t = 400'000;
  std::vector<float> g(n * 3, 0.0f);
  prior->AddGradient(t, means.data(), deformed.data(), g.data(), pool);
  std::vector<float> scratch(n * 3);
  for (size_t k = 0; k < n * 3; ++k) {
    const double h = 1e-3;
    std::vector<float> d = deformed;
    d[k] += static_cast<float>(h);
    const double up = prior->AddGradient(t, means.data(), d.data(), scratch.data(), pool);
    d[k] -= static_cast<float>(2 * h);
    const double down = prior->AddGradient(t, means.data(), d.data(), scratch.data(), pool);
    EXPECT_NEAR(g[k], (up - down) / (2 * h), 2e-4 + 1e-2 * std::abs(g[k])) << "element " << k;
    if (means[(k / 3) * 3 + 1] > 4 || k / 3 % 3 == 0) EXPECT_EQ(g[k], 0.0f) << "unassigned: no gradient";
  }
}

TEST(MotionPrior, BadOptionsAreInvalidArgument) {
  DriveLog log;
  for (double w : {0.0, -1.0, std::nan(""), 1e5}) {
    MotionPriorOptions o = Options();
    o.weight = w;
    EXPECT_EQ(MotionPrior::Build(log, o).status().code(), absl::StatusCode::kInvalidArgument) << w;
  }
  MotionPriorOptions o = Options();
  o.radius_m = 0;
  EXPECT_EQ(MotionPrior::Build(log, o).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MotionPrior::Build(log, Options()).status().code(), absl::StatusCode::kFailedPrecondition);  // no LiDAR
}

}  // namespace
}  // namespace streetsim::train
