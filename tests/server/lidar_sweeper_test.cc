// The server's LiDAR renderer choice (server/lidar_sweeper.h): cpu unless the
// camera engine is vulkan on a GPU; the Vulkan sweeper (forced onto lavapipe
// here) gives the cpu's ranges.
#include <gtest/gtest.h>

#include <cmath>

#include "render/vulkan/vulkan_engine.h"
#include "server/lidar_sweeper.h"
#include "tests/lidar/lidar_test_scenes.h"

namespace streetsim::server {
namespace {

TEST(LidarSweeper, CpuUnlessTheEngineIsVulkanOnAGpu) {
  for (LidarDevice device : {LidarDevice::kCpu, LidarDevice::kFollowEngine}) {
    absl::StatusOr<std::unique_ptr<LidarSweeper>> s =
        CreateLidarSweeper(Backend::kCpu, device);
    ASSERT_TRUE(s.ok()) << s.status();
    EXPECT_EQ((*s)->device_name().rfind("cpu", 0), 0u) << (*s)->device_name();
  }
  absl::StatusOr<std::unique_ptr<LidarSweeper>> follow =
      CreateLidarSweeper(Backend::kVulkan, LidarDevice::kFollowEngine);
  ASSERT_TRUE(follow.ok()) << follow.status();
  const bool on_cpu = (*follow)->device_name().rfind("cpu", 0) == 0;
  EXPECT_EQ(on_cpu, !HasVulkanGpu()) << (*follow)->device_name();
}

TEST(LidarSweeper, VulkanSweeperMatchesTheCpuOne) {
  if (ListVulkanDevices().empty())
    GTEST_SKIP() << "no Vulkan device";
  const lidar_test::GradScene scene =
      lidar_test::RandomGradScene(7, 400, /*rolling=*/true);
  absl::StatusOr<std::unique_ptr<LidarSweeper>> cpu =
      CreateLidarSweeper(Backend::kCpu, LidarDevice::kCpu);
  absl::StatusOr<std::unique_ptr<LidarSweeper>> vk =
      CreateLidarSweeper(Backend::kVulkan, LidarDevice::kVulkanAnyDevice);
  ASSERT_TRUE(cpu.ok() && vk.ok()) << vk.status();
  EXPECT_EQ((*vk)->device_name().rfind("cpu", 0), std::string::npos);
  LidarRenderOutput a, b;
  for (auto *sweeper : {cpu->get(), vk->get()})
    ASSERT_TRUE(sweeper->Upload(scene.store).ok());
  ASSERT_TRUE((*cpu)->Render(scene.model, scene.sweep, {}, &a).ok());
  ASSERT_TRUE((*vk)->Render(scene.model, scene.sweep, {}, &b).ok());
  ASSERT_EQ(a.range.size(), b.range.size());
  size_t returns = 0, both = 0, close = 0;
  for (size_t i = 0; i < a.range.size(); ++i) {
    returns += a.range[i] > 0;
    if (a.range[i] > 0 && b.range[i] > 0) {
      ++both;
      close += std::abs(a.range[i] - b.range[i]) <= 1e-3f * a.range[i];
    }
  }
  EXPECT_GT(returns, 500u);
  // Rays on a return's edge may flip between backends (float order); the rest
  // agree.
  EXPECT_GE(both, returns * 99 / 100);
  EXPECT_GE(close, both * 99 / 100);
  // A bad pose is the renderer's clear error on both.
  LidarSweepPose nan_pose = scene.sweep;
  nan_pose.T_world_from_lidar_start.translation().x() = NAN;
  EXPECT_EQ((*vk)->Render(scene.model, nan_pose, {}, &b).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*cpu)->Render(scene.model, nan_pose, {}, &a).code(),
            absl::StatusCode::kInvalidArgument);
}

} // namespace
} // namespace streetsim::server
