// `streetsim init` through the built binary, viewed with `streetsim render` from a logged camera.
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim {
namespace {

const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
const std::string kData = STREETSIM_DATA_DIR;
const std::string kRaw = kData + "/kitti_raw/2011_09_26";

struct Result {
  int exit_code;
  std::string err;
};

// This process's scratch directory (ctest runs the tests of this file in parallel processes);
// removed when the tests end, pass or fail.
const std::string& Scratch() {
  static const std::string dir = testing::ScratchDir("cli_init", "run");
  return dir;
}

Result Exec(const std::string& args) {
  const std::string err = Scratch() + "/stderr.txt";
  const int status = std::system((kBinary + " " + args + " >/dev/null 2>" + err).c_str());
  std::ifstream f(err);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1,
          std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>())};
}

double Psnr(const cv::Mat& a, const cv::Mat& b) {
  cv::Mat da, db;
  a.convertTo(da, CV_64F, 1 / 255.0);
  b.convertTo(db, CV_64F, 1 / 255.0);
  const cv::Mat d = da - db;
  const double mse = cv::sum(d.mul(d))[0] + cv::sum(d.mul(d))[1] + cv::sum(d.mul(d))[2];
  return 10 * std::log10(1.0 / (mse / (3.0 * a.total())));
}

TEST(CliInit, InitialSceneRendersLikeTheLoggedImage) {
  const std::string dir = testing::ScratchDir("cli_init", "render");
  const std::string ply = dir + "/init.ply", cam = dir + "/cam20.json", png = dir + "/render20.png";
  Result r = Exec("init " + kRaw + " --out " + ply + " --frames 0:40 --voxel 0.1 --sky");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.err.find("Gaussians from lidar"), std::string::npos) << r.err;
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(ply);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_GT(store->size(), 50'000u);
  r = Exec("log camera " + kRaw + " --frame 20 --out " + cam);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  r = Exec("render --backend cpu --ply " + ply + " --camera " + cam + " --out-rgb " + png);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const cv::Mat render = cv::imread(png);
  const cv::Mat image = cv::imread(kRaw + "/2011_09_26_drive_sfnd_sync/image_02/data/0000000020.png");
  ASSERT_EQ(render.size(), image.size());
  const double psnr = Psnr(render, image);
  const double blank = Psnr(cv::Mat::zeros(image.size(), image.type()), image);
  std::printf("streetsim render of the init from logged camera 20: PSNR %.2f dB (black image %.2f dB)\n", psnr, blank);
  EXPECT_GT(psnr, blank + 4);
}

TEST(CliInit, SceneDirectoryGetsTheLogManifest) {
  // DIR/scene.ply -> DIR/scene.json with the rig, time range and trajectory the server serves.
  const std::string dir = testing::ScratchDir("cli_init", "scene");
  const Result r = Exec("init " + kRaw + " --out " + dir + "/scene.ply --frames 0:10 --voxel 0.3");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  std::ifstream f(dir + "/scene.json");
  const std::string json((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  EXPECT_NE(json.find("\"ego_trajectory\""), std::string::npos) << json.substr(0, 200);
  EXPECT_NE(json.find("\"image_02\""), std::string::npos);
  EXPECT_NE(json.find("\"time_range_us\""), std::string::npos);
  // Any other output name writes no manifest.
  ASSERT_EQ(Exec("init " + kRaw + " --out " + dir + "/other.ply --frames 0:10 --voxel 0.3").exit_code, 0);
  EXPECT_FALSE(std::filesystem::exists(dir + "/other.json"));
}

TEST(CliInit, CameraOnlyLogSaysItsPointsAreTriangulated) {
  const std::string ply = Scratch() + "/triangulated.ply";
  const Result r = Exec("init " + kData + "/kitti_odometry_excerpt/seq_a --out " + ply + " --frames 0:5");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.err.find("from triangulated"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("points triangulated with the log's poses"), std::string::npos) << r.err;
}

TEST(CliInit, BadInputIsExitTwoAndOneLine) {
  const std::string out = Scratch() + "/x.ply";
  for (const auto& [args, says] : std::vector<std::pair<std::string, std::string>>{
           {"init", "expects exactly one log PATH"},
           {"init " + kRaw, "--out is required"},
           {"init " + kRaw + " --out x.png", "must be a .ply"},
           {"init " + kRaw + " --out " + out + " --voxel -1", "--voxel must be a positive number"},
           {"init " + kRaw + " --out " + out + " --frames 10", "--frames '10'"},
           {"init " + kRaw + " --out " + out + " --frames 500:600", "no frames selected"},
           {"init " + kData + "/nope --out " + out, "no such file or directory"},
           {"init " + kRaw + " --out " + out + " --sky=1", "--sky takes no value"},
       }) {
    const Result r = Exec(args);
    EXPECT_EQ(r.exit_code, 2) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
    EXPECT_NE(r.err.find(says), std::string::npos) << args << ": " << r.err;
  }
}

}  // namespace
}  // namespace streetsim
