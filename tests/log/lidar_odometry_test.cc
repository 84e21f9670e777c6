// LiDAR odometry: the k-d tree against brute force, ICP on a known motion, and the estimate on a
// subset of the shared KITTI clip against the provided poses (the full clip: lidar_odometry_long_test).
#include <chrono>
#include <cstdio>
#include <algorithm>
#include <cmath>
#include <map>
#include <random>
#include <tuple>

#include "gtest/gtest.h"
#include "scene/log/kdtree.h"
#include "scene/log/lidar_odometry.h"
#include "scene/log/open_log.h"
#include "scene/log/voxel_hash.h"

namespace streetsim {
namespace {

const std::string kRaw = std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

// The filter's flat table against the plain definition (a map from voxel to its first place,
// sums in point order): the same centroids in the same order, bit for bit, across repeated
// calls of different sizes on one thread (the thread keeps its table) and above the size it
// keeps (2^21 points).
TEST(VoxelDownsample, EqualsTheMapDefinition) {
  const auto reference = [](const std::vector<Eigen::Vector3f>& points, double voxel_m) {
    std::map<std::tuple<int32_t, int32_t, int32_t>, size_t> slot;
    std::vector<Eigen::Vector3d> sum;
    std::vector<int> count;
    for (const Eigen::Vector3f& p : points) {
      const VoxelKey k = VoxelOf(p.cast<double>(), 1.0 / voxel_m);
      auto [it, inserted] = slot.try_emplace({k.x, k.y, k.z}, sum.size());
      if (inserted) {
        sum.push_back(p.cast<double>());
        count.push_back(1);
      } else {
        sum[it->second] += p.cast<double>();
        ++count[it->second];
      }
    }
    std::vector<Eigen::Vector3f> out;
    for (size_t i = 0; i < sum.size(); ++i) out.push_back((sum[i] / count[i]).cast<float>());
    return out;
  };
  std::mt19937 rng(11);
  for (size_t n : {size_t{100000}, size_t{3}, size_t{0}, size_t{20000}, (size_t{1} << 21) + 5}) {
    std::uniform_real_distribution<float> u(-20, 20);
    std::vector<Eigen::Vector3f> points(n);
    for (auto& p : points) p = {u(rng), u(rng), u(rng) * 0.05f};  // a thin slab: many shared voxels
    const double voxel_m = n > 100000 ? 0.5 : 0.05;
    const std::vector<Eigen::Vector3f> got = VoxelDownsample(points, voxel_m);
    const std::vector<Eigen::Vector3f> want = reference(points, voxel_m);
    ASSERT_EQ(got.size(), want.size()) << n;
    for (size_t i = 0; i < got.size(); ++i) ASSERT_EQ(got[i], want[i]) << n << " points, voxel " << i;
  }
}

// The index grows from its smallest table: every key keeps the index it was first given (found
// by FindOrInsert and Find; an absent key is not found), and Clear() starts over.
TEST(VoxelIndex, KeepsFirstSeenIndicesAcrossGrowth) {
  VoxelIndex index;
  std::map<std::tuple<int32_t, int32_t, int32_t>, int32_t> want;
  std::mt19937 rng(5);
  std::uniform_int_distribution<int32_t> u(-300, 300);
  for (int round = 0; round < 2; ++round) {
    for (int i = 0; i < 200000; ++i) {
      const VoxelKey k{u(rng), u(rng), u(rng) / 100};
      bool inserted = false;
      const int32_t got = index.FindOrInsert(k, &inserted);
      auto [it, is_new] = want.try_emplace({k.x, k.y, k.z}, static_cast<int32_t>(want.size()));
      ASSERT_EQ(inserted, is_new) << i;
      ASSERT_EQ(got, it->second) << i;
      ASSERT_EQ(index.Find(k), it->second) << i;
      ASSERT_EQ(index.Find(VoxelKey{k.x, k.y, 1000}), -1) << i;  // z in -3..3 only
    }
    ASSERT_EQ(index.size(), want.size());
    index.Clear(10);
    want.clear();
    EXPECT_EQ(index.size(), 0u);
  }
}

TEST(KdTree, AgreesWithBruteForce) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<float> u(-10, 10);
  std::vector<Eigen::Vector3f> pts(5000);
  for (auto& p : pts) p = {u(rng), u(rng), u(rng) * 0.1f};
  KdTree3 tree(&pts);
  for (int q = 0; q < 200; ++q) {
    const Eigen::Vector3f query(u(rng), u(rng), u(rng) * 0.1f);
    std::vector<std::pair<float, int>> all;
    for (size_t i = 0; i < pts.size(); ++i) all.emplace_back((pts[i] - query).squaredNorm(), static_cast<int>(i));
    std::sort(all.begin(), all.end());
    float d;
    EXPECT_EQ(tree.Nearest(query, 1e9f, &d), all[0].second);
    int idx[8];
    float d2[8];
    ASSERT_EQ(tree.KNearest(query, 8, 1e9f, idx, d2), 8);
    for (int k = 0; k < 8; ++k) EXPECT_EQ(idx[k], all[k].second);
    // A radius that holds none.
    EXPECT_EQ(tree.Nearest(query, all[0].first * 0.5f), -1);
  }
}

TEST(Icp, RecoversAKnownMotionOnARealScan) {
  absl::StatusOr<DriveLog> log = OpenLog(kRaw);
  ASSERT_TRUE(log.ok()) << log.status();
  absl::StatusOr<LidarScan> scan = LoadLidarScan(log->frames[10].lidars[0].path);
  ASSERT_TRUE(scan.ok());
  const LidarOdometryOptions options;
  const std::vector<Eigen::Vector3f> points = RangeFilter(scan->points, options.min_range_m, options.max_range_m);
  PlaneCloud target;
  BuildPlaneCloud(points, options, &target);
  Eigen::Isometry3d truth = Eigen::Isometry3d::Identity();
  truth.linear() = Eigen::AngleAxisd(0.03, Eigen::Vector3d(0.1, 0.2, 1).normalized()).toRotationMatrix();
  truth.translation() << 0.6, -0.15, 0.03;
  std::vector<Eigen::Vector3f> moved;
  for (const Eigen::Vector3f& p : points) moved.push_back((truth.inverse() * p.cast<double>()).cast<float>());
  const IcpResult icp = PointToPlaneIcp(target, VoxelDownsample(moved, options.source_voxel_m),
                                        Eigen::Isometry3d::Identity(), options);
  const Eigen::Isometry3d err = truth.inverse() * icp.T_target_from_source;
  EXPECT_LT(err.translation().norm(), 0.01);
  EXPECT_LT(Eigen::AngleAxisd(err.linear()).angle(), 0.1 * M_PI / 180);
  EXPECT_TRUE(icp.converged);
}

TEST(CompareTrajectories, DriftOfAScaledTrack) {
  std::vector<Eigen::Isometry3d> ref, est;
  for (int i = 0; i <= 10; ++i) {
    Eigen::Isometry3d r = Eigen::Isometry3d::Identity(), e = r;
    r.translation() << i * 10.0, 0, 0;
    e.translation() << i * 10.1, 0, 0;
    ref.push_back(r);
    est.push_back(e);
  }
  const TrajectoryComparison c = CompareTrajectories(est, ref);
  EXPECT_NEAR(c.reference_distance_m, 100, 1e-9);
  EXPECT_NEAR(c.final_translation_error_m, 1.0, 1e-9);
  EXPECT_NEAR(c.drift_percent, 1.0, 1e-9);
  EXPECT_NEAR(c.mean_relative_translation_error_m, 0.1, 1e-9);
}

// The first 30 frames (3 s, ~3.3 m) of the clip against poses_velo_icp_estimated.txt. Both are
// estimates; the bound says they agree to tens of centimetres, the numbers go to docs/logs.md.
TEST(LidarOdometry, AgreesWithTheProvidedEstimateOnASubset) {
  absl::StatusOr<DriveLog> log = OpenLog(kRaw);
  ASSERT_TRUE(log.ok()) << log.status();
  LidarOdometryOptions options;
  options.last_frame = 30;
  absl::StatusOr<LidarOdometryResult> odo = RunLidarOdometry(*log, options);
  ASSERT_TRUE(odo.ok()) << odo.status();
  ASSERT_EQ(odo->frames.size(), 30u);
  EXPECT_TRUE(odo->problems.empty());
  std::vector<Eigen::Isometry3d> reference;
  for (int f : odo->frames) reference.push_back(log->frames[f].T_world_from_ego);
  const TrajectoryComparison c = CompareTrajectories(odo->T_world_from_ego, reference);
  std::printf("30 frames: %.2f m driven, end error %.3f m (%.1f%%), max %.3f m, end rotation %.2f deg, "
              "per-frame %.3f m / %.3f deg, %.1f ms per scan\n",
              c.reference_distance_m, c.final_translation_error_m, c.drift_percent,
              c.max_translation_error_m, c.final_rotation_error_deg, c.mean_relative_translation_error_m,
              c.mean_relative_rotation_error_deg, odo->ms_per_scan);
  EXPECT_GT(c.reference_distance_m, 2.5);
  EXPECT_LT(c.max_translation_error_m, 0.8);
  EXPECT_LT(c.final_rotation_error_deg, 2.5);
  EXPECT_LT(c.mean_relative_translation_error_m, 0.06);
  for (size_t i = 1; i < odo->icp.size(); ++i) EXPECT_GT(odo->icp[i].inliers, 1000) << i;
}

}  // namespace
}  // namespace streetsim
