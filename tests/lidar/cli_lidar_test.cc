// streetsim render --lidar end to end: a wall scene written as PLY, a POSE.json, the outputs read back.
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "render/lidar/lidar_model.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim {
namespace {

const std::string kBin = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";

int RunCli(const std::string& args, std::string* err = nullptr) {
  static const std::string io_dir = testing::ScratchDir("cli_lidar", "io");
  const std::string log = io_dir + "/stderr.txt";
  const int rc = std::system((kBin + " " + args + " 2> " + log).c_str());
  std::ifstream f(log);
  const std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  if (err) *err = text;
  return WEXITSTATUS(rc);
}

TEST(CliLidar, RendersAWallToTiffPngAndPly) {
  const std::string dir = testing::ScratchDir("cli_lidar", "wall");
  // A wall 12 m ahead of a sensor at (5, 2, 1.7) in the world (plane x = 17).
  GaussianStore s;
  for (double y = -4; y <= 8; y += 0.05) {
    for (double z = 0; z <= 4; z += 0.05) {
      s.means.insert(s.means.end(), {17.0f, static_cast<float>(y), static_cast<float>(z)});
      s.log_scales.insert(s.log_scales.end(), {std::log(0.005f), std::log(0.05f), std::log(0.05f)});
      s.rotations.insert(s.rotations.end(), {1, 0, 0, 0});
      s.opacity_logits.push_back(1.0f);
      s.sh.insert(s.sh.end(), {0, 0, 0});
    }
  }
  ASSERT_TRUE(WriteGaussianPly(s, dir + "/wall.ply").ok());
  std::ofstream(dir + "/pose.json") << R"({"T_world_from_lidar": [1,0,0,5, 0,1,0,2, 0,0,1,1.7, 0,0,0,1], "time_us": 1000000})";
  std::string err;
  ASSERT_EQ(RunCli("render --lidar --ply " + dir + "/wall.ply --pose " + dir + "/pose.json --out-range " + dir +
                    "/r.tiff --out-lidar-png " + dir + "/r.png --out-points " + dir + "/p.ply",
                &err),
            0)
      << err;
  std::printf("%s", err.c_str());
  const cv::Mat range = cv::imread(dir + "/r.tiff", cv::IMREAD_UNCHANGED);
  ASSERT_EQ(range.type(), CV_32FC1);
  ASSERT_EQ(range.rows, 64);
  ASSERT_EQ(range.cols, 2048);
  const LidarModel m = KittiHdl64e(2048);
  // Beam 10 straight ahead (column 1023): 12 / (cos el cos az).
  const Eigen::Vector3d d = m.RayDirection(10, 1023);
  EXPECT_NEAR(range.at<float>(10, 1023), 12.0 / d.x(), 0.02);
  EXPECT_EQ(range.at<float>(10, 0), 0.0f);  // behind: nothing
  const cv::Mat png = cv::imread(dir + "/r.png", cv::IMREAD_COLOR);
  ASSERT_EQ(png.rows, 64);
  ASSERT_EQ(png.cols, 2048);
  EXPECT_EQ(png.at<cv::Vec3b>(10, 0), cv::Vec3b(0, 0, 0));
  EXPECT_NE(png.at<cv::Vec3b>(10, 1023), cv::Vec3b(0, 0, 0));
  std::ifstream ply(dir + "/p.ply", std::ios::binary);
  std::string line;
  size_t n = 0;
  while (std::getline(ply, line) && line != "end_header") {
    if (line.rfind("element vertex ", 0) == 0) n = std::stoul(line.substr(15));
  }
  EXPECT_EQ(n, static_cast<size_t>(cv::countNonZero(range)));
  // The bad-argument contract: exit 2, one line naming the problem.
  EXPECT_EQ(RunCli("render --lidar --ply " + dir + "/wall.ply --pose " + dir + "/pose.json", &err), 2);
  EXPECT_NE(err.find("--out-range"), std::string::npos) << err;
  std::ofstream(dir + "/bad.json") << R"({"T_world_from_lidar": [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]})";
  EXPECT_EQ(RunCli("render --lidar --ply " + dir + "/wall.ply --pose " + dir + "/bad.json --out-range " + dir + "/x.tiff", &err), 2);
  EXPECT_NE(err.find("rigid"), std::string::npos) << err;
}

}  // namespace
}  // namespace streetsim
