// scene.json is written by scene/ (streetsim init / train) and read by the server: the two sides
// of one file format must agree.
#include "gtest/gtest.h"
#include "scene/log/open_log.h"
#include "scene/log/scene_manifest.h"
#include "server/scene_manifest.h"

namespace streetsim {
namespace {

TEST(SceneManifestCompat, ServerReadsWhatALogWrites) {
  absl::StatusOr<DriveLog> log =
      OpenLog(std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync");
  ASSERT_TRUE(log.ok()) << log.status();
  absl::StatusOr<server::SceneManifest> m = server::ParseSceneManifest(SceneManifestJson(*log, "kitti"));
  ASSERT_TRUE(m.ok()) << m.status();
  ASSERT_TRUE(m->has_time_range);
  EXPECT_EQ(m->start_us, log->frames.front().time_us);
  EXPECT_EQ(m->end_us, log->frames.back().time_us);
  ASSERT_EQ(m->cameras.size(), log->cameras.size());
  EXPECT_EQ(m->cameras[0].sensor_id, log->cameras[0].name);
  EXPECT_TRUE(m->cameras[0].T_ego_from_cam.isApprox(log->cameras[0].T_ego_from_cam, 1e-12));
  ASSERT_EQ(m->ego_trajectory.size(), log->frames.size());
  for (size_t i = 0; i < log->frames.size(); ++i) {
    EXPECT_EQ(m->ego_trajectory[i].time_us, log->frames[i].time_us);
    EXPECT_TRUE(m->ego_trajectory[i].T_world_from_ego.isApprox(log->frames[i].T_world_from_ego, 1e-12)) << i;
  }
  ASSERT_EQ(m->lidars.size(), log->lidars.size());
  ASSERT_FALSE(m->lidars.empty());
  EXPECT_EQ(m->lidars[0].sensor_id, log->lidars[0].name);
  EXPECT_TRUE(m->lidars[0].T_ego_from_lidar.isApprox(log->lidars[0].T_ego_from_lidar, 1e-12));
  // And the server writes back what it read.
  absl::StatusOr<server::SceneManifest> again = server::ParseSceneManifest(server::SceneManifestToJson(*m));
  ASSERT_TRUE(again.ok()) << again.status();
  ASSERT_EQ(again->lidars.size(), m->lidars.size());
  EXPECT_TRUE(again->lidars[0].T_ego_from_lidar.isApprox(m->lidars[0].T_ego_from_lidar, 1e-12));
  // Between two logged frames the server interpolates the log's pose.
  const int64_t mid = (log->frames[10].time_us + log->frames[11].time_us) / 2;
  const Eigen::Vector3d expected =
      0.5 * (log->frames[10].T_world_from_ego.translation() + log->frames[11].T_world_from_ego.translation());
  EXPECT_LT((m->EgoPoseAt(mid)->translation() - expected).norm(), 1e-6);
}

}  // namespace
}  // namespace streetsim
