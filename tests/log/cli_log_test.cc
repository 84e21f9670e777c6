// `streetsim log ...` through the built binary: every shared log, and clean refusals.
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <string>

#include "gtest/gtest.h"
#include "nlohmann/json.hpp"
#include "scene/log/poses_file.h"
#include "tests/common/scratch_dir.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;
const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
const std::string kData = STREETSIM_DATA_DIR;

struct Result {
  int exit_code;
  std::string out, err;
};

std::string Slurp(const std::string& p) {
  std::ifstream f(p);
  return std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
}

// This process's scratch directory (ctest runs the tests of this file in parallel processes);
// removed when the tests end.
const std::string& Scratch() {
  static const std::string dir = testing::ScratchDir("cli_log", "run");
  return dir;
}

Result Exec(const std::string& args) {
  const std::string out = Scratch() + "/stdout.txt";
  const std::string err = Scratch() + "/stderr.txt";
  const int status = std::system((kBinary + " " + args + " >" + out + " 2>" + err).c_str());
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, Slurp(out), Slurp(err)};
}

int Lines(const std::string& s) {
  int n = 0;
  for (char c : s) n += c == '\n';
  return n;
}

// The refusal names its command: "streetsim log info: ..." (a file-local helper of another
// command once answered for log's under a unity build, as "streetsim info: ...").
std::string CommandPrefix(const std::string& args) {
  std::istringstream words(args);
  std::string log, sub;
  words >> log >> sub;
  for (const char* known : {"info", "preview", "poses", "tracks"}) {
    if (sub == known) return "streetsim log " + sub + ": ";
  }
  return "streetsim log";
}

void ExpectRefusal(const std::string& args, const std::string& says) {
  const Result r = Exec(args);
  EXPECT_EQ(r.exit_code, 2) << args << ": " << r.err;
  EXPECT_EQ(Lines(r.err), 1) << args << ": " << r.err;
  EXPECT_NE(r.err.find(says), std::string::npos) << args << ": " << r.err;
  EXPECT_EQ(r.err.rfind(CommandPrefix(args), 0), 0u) << args << ": " << r.err;
}

TEST(CliLog, InfoWorksOnEverySharedLog) {
  const std::vector<std::pair<std::string, std::string>> logs = {
      {"/kitti_raw/2011_09_26", "frames: 78"},
      {"/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync", "lidars: 1"},
      {"/kitti_oxts/2011_09_26/2011_09_26_drive_0013_sync", "world: ENU at lat 49.013141873"},
      {"/kitti_oxts/2011_09_26/2011_09_26_drive_0013_gps_loss", "42 of 144 oxts records bridged"},
      {"/kitti_oxts/2011_09_26/2011_09_26_drive_0013_gps_loss/oxts", "frames: 144"},
      {"/kitti_odometry_excerpt/seq_a", "frames: 51"},
      {"/colmap_plush", "sparse points: 25784"},
  };
  for (const auto& [path, says] : logs) {
    const Result r = Exec("log info " + kData + path);
    EXPECT_EQ(r.exit_code, 0) << path << ": " << r.err;
    EXPECT_NE(r.out.find(says), std::string::npos) << path << ":\n" << r.out;
    EXPECT_NE(r.out.find("distance driven:"), std::string::npos);
    EXPECT_NE(r.out.find("time span:"), std::string::npos);
  }
}

TEST(CliLog, PreviewDrawsLidarOnTheImage) {
  const std::string out = Scratch() + "/preview.png";
  fs::remove(out);
  const Result r = Exec("log preview " + kData + "/kitti_raw/2011_09_26 --frame 10 --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const cv::Mat drawn = cv::imread(out);
  const cv::Mat original = cv::imread(kData + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync/image_02/data/0000000010.png");
  ASSERT_EQ(drawn.size(), original.size());
  cv::Mat diff;
  cv::absdiff(drawn, original, diff);
  cv::cvtColor(diff, diff, cv::COLOR_BGR2GRAY);
  // Thousands of LiDAR dots, and the sky (top rows, above the HDL-64's +2 degrees) untouched.
  EXPECT_GT(cv::countNonZero(diff > 30), 20'000);
  EXPECT_EQ(cv::countNonZero(diff(cv::Rect(0, 0, drawn.cols, 20)) > 30), 0);
  // Camera-only logs draw their sparse points.
  EXPECT_EQ(Exec("log preview " + kData + "/colmap_plush --frame 3 --out " + out).exit_code, 0);
  fs::remove(out);
}

TEST(CliLog, PosesFromLidarCompareWithTheProvidedEstimate) {
  const std::string out = Scratch() + "/poses.txt";
  const Result r = Exec("log poses " + kData + "/kitti_raw/2011_09_26 --from-lidar --frames 0:12 --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.out.find("against poses_velo_icp_estimated.txt"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("ms per scan"), std::string::npos);
  absl::StatusOr<std::vector<Eigen::Isometry3d>> poses = ReadPosesFile(out);
  ASSERT_TRUE(poses.ok()) << poses.status();
  EXPECT_EQ(poses->size(), 12u);
  fs::remove(out);
}

TEST(CliLog, CameraWritesARenderableCamera) {
  const std::string out = Scratch() + "/cam.json";
  const Result r = Exec("log camera " + kData + "/kitti_odometry_excerpt/seq_a --frame 5 --out " + out);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(Slurp(out).find("\"width\": 1226"), std::string::npos) << Slurp(out);
  fs::remove(out);
}

// The clip's tanker, followed in the LiDAR alone: the object with the most points when first seen
// (beside the ego car on the right), about 9.5 m in the world over frames 0-39 by the right lane's
// occupancy (docs/benchmarks.md "Where the held-out error is", session 22).
TEST(CliLog, TracksFollowTheTanker) {
  const std::string out = Scratch() + "/tracks.json";
  const Result r = Exec("log tracks " + kData + "/kitti_raw/2011_09_26 --frames 0:40 --json " + out);
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.out.find("| id | frames | scans | moved (m)"), std::string::npos) << r.out;
  const nlohmann::json j = nlohmann::json::parse(Slurp(out));
  EXPECT_EQ(j["frames_used"], 40);
  ASSERT_FALSE(j["tracks"].empty());
  const nlohmann::json* tanker = nullptr;
  for (const nlohmann::json& t : j["tracks"]) {
    if (tanker == nullptr || t["observations"][0]["num_points"] > (*tanker)["observations"][0]["num_points"]) {
      tanker = &t;
    }
  }
  ASSERT_EQ((*tanker)["observations"].size(), 40u);
  const double moved = (*tanker)["net_displacement_m"];
  EXPECT_GT(moved, 8.0);
  EXPECT_LT(moved, 11.5);
  const double y = (*tanker)["observations"][0]["centroid_world"][1];
  EXPECT_LT(y, -1.5) << "the tanker is on the right";
  fs::remove(out);
  // An unwritable --json: exit 1 and one line naming it, nothing left behind.
  const Result bad = Exec("log tracks " + kData + "/kitti_raw/2011_09_26 --frames 0:3 --json /nonexistent_dir/t.json");
  EXPECT_EQ(bad.exit_code, 1) << bad.err;
  EXPECT_EQ(Lines(bad.err), 1) << bad.err;
  EXPECT_NE(bad.err.find("/nonexistent_dir/t.json"), std::string::npos) << bad.err;
}

TEST(CliLog, BadInputIsExitTwoAndOneLine) {
  ExpectRefusal("log", "expects a subcommand");
  ExpectRefusal("log frobnicate x", "unknown subcommand");
  ExpectRefusal("log info", "expects exactly one log PATH");
  ExpectRefusal("log info " + kData + "/nope", "no such file or directory");
  ExpectRefusal("log info " + kData + "/ply", "not a recognised log");
  ExpectRefusal("log info " + kData + "/kitti_oxts/2011_09_26", "name one");
  ExpectRefusal("log info " + kData + "/colmap_plush --bogus", "unknown flag --bogus");
  ExpectRefusal("log preview " + kData + "/kitti_raw/2011_09_26 --frame 500 --out /tmp/x.png", "--frame 500 is not in 0..77");
  ExpectRefusal("log preview " + kData + "/kitti_raw/2011_09_26 --frame 1", "--out is required");
  ExpectRefusal("log preview " + kData + "/kitti_raw/2011_09_26 --out x.jpg", "must be a .png");
  ExpectRefusal("log preview " + kData + "/kitti_odometry_excerpt/seq_a --out /tmp/x.png", "no LiDAR and no sparse points");
  ExpectRefusal("log poses " + kData + "/kitti_odometry_excerpt/seq_a --from-lidar", "no LiDAR");
  ExpectRefusal("log poses " + kData + "/kitti_raw/2011_09_26 --frames 5:2", "--frames '5:2'");
  ExpectRefusal("log tracks " + kData + "/colmap_plush", "no LiDAR");
  ExpectRefusal("log tracks " + kData + "/kitti_raw/2011_09_26 --frames 0:40:2", "stride 1");
  ExpectRefusal("log tracks " + kData + "/kitti_raw/2011_09_26 --frames 5:6", "fewer than 2 frames");
  ExpectRefusal("log tracks " + kData + "/kitti_raw/2011_09_26 --min-scans 0", "--min-scans");
  ExpectRefusal("log tracks " + kData + "/kitti_raw/2011_09_26 --min-displacement-m nan", "--min-displacement-m");
  ExpectRefusal("log tracks " + kData + "/kitti_raw/2011_09_26 --json", "--json");
}

}  // namespace
}  // namespace streetsim
