// The whole 78-frame clip against the provided estimate (ctest label `long`).
#include <cstdio>

#include "gtest/gtest.h"
#include "scene/log/lidar_odometry.h"
#include "scene/log/open_log.h"

namespace streetsim {
namespace {

TEST(LidarOdometryLong, WholeClipAgainstTheProvidedEstimate) {
  absl::StatusOr<DriveLog> log =
      OpenLog(std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync");
  ASSERT_TRUE(log.ok()) << log.status();
  absl::StatusOr<LidarOdometryResult> odo = RunLidarOdometry(*log);
  ASSERT_TRUE(odo.ok()) << odo.status();
  std::vector<Eigen::Isometry3d> reference;
  for (int f : odo->frames) reference.push_back(log->frames[f].T_world_from_ego);
  const TrajectoryComparison c = CompareTrajectories(odo->T_world_from_ego, reference);
  std::printf("78 frames: %.2f m driven, end error %.3f m (%.1f m per 100 m, extrapolated), max %.3f m, "
              "end rotation %.2f deg, per-frame %.3f m / %.3f deg, %.1f ms per scan\n",
              c.reference_distance_m, c.final_translation_error_m, c.drift_percent,
              c.max_translation_error_m, c.final_rotation_error_deg, c.mean_relative_translation_error_m,
              c.mean_relative_rotation_error_deg, odo->ms_per_scan);
  EXPECT_LT(c.max_translation_error_m, 1.2);
  EXPECT_LT(c.final_rotation_error_deg, 2.5);
  EXPECT_LT(c.mean_relative_translation_error_m, 0.05);
}

}  // namespace
}  // namespace streetsim
