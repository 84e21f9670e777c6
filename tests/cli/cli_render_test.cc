// The `streetsim render` contract, exercised through the real binary.
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "client/cli/camera_json.h"
#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "render/cpu/cpu_engine.h"
#include "scene/gaussians/ply_io.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;

const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
const std::string kPly = std::string(STREETSIM_DATA_DIR) + "/ply/inria_sh3_9080.ply";

struct ProcessResult {
  int exit_code;
  std::string stderr_text;
};

ProcessResult Exec(const std::string& args) {
  // Per process (ctest runs the tests of this file in parallel processes); removed at the end.
  static const std::string io_dir = testing::ScratchDir("cli_render", "io");
  const std::string err = io_dir + "/stderr.txt";
  const std::string cmd = kBinary + " " + args + " 2>" + err + " >/dev/null";
  const int status = std::system(cmd.c_str());
  std::ifstream f(err);
  std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, text};
}

int Lines(const std::string& s) {
  int n = 0;
  for (char c : s) n += c == '\n';
  return n;
}

class CliRender : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::ScratchDir("cli_render", ::testing::UnitTest::GetInstance()->current_test_info()->name());
    camera_ = dir_ + "/camera.json";
    const ProcessResult r = Exec("ply-info " + kPly + " --camera-out " + camera_ + " --width 320 --height 240");
    ASSERT_EQ(r.exit_code, 0) << r.stderr_text;
  }
  void WriteFile(const std::string& path, const std::string& text) {
    std::ofstream f(path, std::ios::binary);
    f << text;
  }
  // Expects a clean refusal: the given non-zero exit, one line on stderr naming the problem, and
  // no output file.
  void ExpectRefused(const std::string& args, int code, const std::string& needle) {
    const std::string out = dir_ + "/refused.png";
    const ProcessResult r = Exec("render " + args + (args.find("--out-rgb") == std::string::npos ? " --out-rgb " + out : ""));
    EXPECT_EQ(r.exit_code, code) << args << "\n" << r.stderr_text;
    EXPECT_EQ(Lines(r.stderr_text), 1) << r.stderr_text;
    EXPECT_NE(r.stderr_text.find(needle), std::string::npos) << "wanted '" << needle << "' in: " << r.stderr_text;
    EXPECT_FALSE(fs::exists(out));
  }
  std::string dir_, camera_;
};

TEST_F(CliRender, WritesPngAndFloatTiffsMatchingTheEngine) {
  const std::string rgb = dir_ + "/out.png", depth = dir_ + "/d.tiff", alpha = dir_ + "/a.tif";
  const ProcessResult r = Exec("render --ply " + kPly + " --camera " + camera_ + " --out-rgb " + rgb +
                     " --out-depth " + depth + " --out-alpha " + alpha + " --backend cpu");
  ASSERT_EQ(r.exit_code, 0) << r.stderr_text;

  const cv::Mat png = cv::imread(rgb, cv::IMREAD_UNCHANGED);
  ASSERT_EQ(png.type(), CV_8UC3);
  ASSERT_EQ(png.cols, 320);
  ASSERT_EQ(png.rows, 240);
  const cv::Mat d = cv::imread(depth, cv::IMREAD_UNCHANGED), a = cv::imread(alpha, cv::IMREAD_UNCHANGED);
  ASSERT_EQ(d.type(), CV_32FC1);
  ASSERT_EQ(a.type(), CV_32FC1);

  // Same render through the API: the PNG holds round(clamp(rgb) * 255) in R, G, B order.
  auto store = ReadGaussianPly(kPly);
  ASSERT_TRUE(store.ok());
  auto cam = ReadCameraJson(camera_);
  ASSERT_TRUE(cam.ok());
  auto engine = CreateCpuEngine();
  auto scene = engine->Upload(*store);
  RenderOutput out;
  ASSERT_TRUE(engine->Render(**scene, *cam, {}, &out).ok());
  int covered = 0;
  for (int v = 0; v < 240; ++v) {
    for (int u = 0; u < 320; ++u) {
      const size_t p = static_cast<size_t>(v) * 320 + u;
      const cv::Vec3b bgr = png.at<cv::Vec3b>(v, u);
      for (int c = 0; c < 3; ++c) {
        const int want = static_cast<int>(std::lround(std::clamp(out.rgb[p * 3 + c], 0.0f, 1.0f) * 255));
        ASSERT_EQ(bgr[2 - c], want) << u << "," << v << " channel " << c;
      }
      ASSERT_FLOAT_EQ(a.at<float>(v, u), out.alpha[p]);
      ASSERT_FLOAT_EQ(d.at<float>(v, u), out.depth[p]);
      covered += out.alpha[p] > 0.5f;
    }
  }
  EXPECT_GT(covered, 320 * 240 / 10);  // the framing camera sees the scene
}

TEST_F(CliRender, BackgroundFillsEmptyPixels) {
  // A camera looking away from the scene sees only the background.
  auto cam = ReadCameraJson(camera_);
  ASSERT_TRUE(cam.ok());
  cam->T_world_from_cam.linear() = cam->T_world_from_cam.linear() * Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitY());
  WriteFile(dir_ + "/away.json", CameraToJson(*cam));
  const std::string rgb = dir_ + "/bg.png";
  const ProcessResult r = Exec("render --ply " + kPly + " --camera " + dir_ + "/away.json --out-rgb " + rgb +
                     " --background 1,0.5,0 --backend cpu");
  ASSERT_EQ(r.exit_code, 0) << r.stderr_text;
  const cv::Mat png = cv::imread(rgb, cv::IMREAD_UNCHANGED);
  const cv::Vec3b corner = png.at<cv::Vec3b>(0, 0);
  EXPECT_EQ(corner[2], 255);
  EXPECT_EQ(corner[1], 128);
  EXPECT_EQ(corner[0], 0);
}

TEST_F(CliRender, RefusesBadArguments) {
  const std::string base = "--ply " + kPly + " --camera " + camera_;
  ExpectRefused("--camera " + camera_, 2, "--ply is required");
  ExpectRefused("--ply " + kPly, 2, "--camera is required");
  ExpectRefused(base + " --out-rgb", 2, "needs a value");
  ExpectRefused(base + " --frobnicate 1", 2, "unknown flag --frobnicate");
  ExpectRefused(base + " extra", 2, "unexpected argument");
  ExpectRefused(base + " --background 1,2", 2, "R,G,B");
  ExpectRefused(base + " --background a,0,0", 2, "not a number in [0,1]");
  ExpectRefused(base + " --background 2,0,0", 2, "not a number in [0,1]");
  ExpectRefused(base + " --backend metal", 2, "unknown backend 'metal'");
  ExpectRefused(base + " --out-rgb " + dir_ + "/x.bmp", 2, "unsupported extension");
  ExpectRefused(base + " --out-depth " + dir_ + "/d.png", 2, "unsupported extension");
  ExpectRefused("--ply /nonexistent/scene.ply --camera " + camera_, 2, "/nonexistent/scene.ply");
  ExpectRefused("--ply " + kPly + " --camera /nonexistent/cam.json", 2, "cannot open camera file");
}

TEST_F(CliRender, RefusesBadFiles) {
  // Truncated PLY.
  std::ifstream in(kPly, std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  WriteFile(dir_ + "/truncated.ply", bytes.substr(0, bytes.size() / 2));
  ExpectRefused("--ply " + dir_ + "/truncated.ply --camera " + camera_, 2, "truncated.ply");
  WriteFile(dir_ + "/garbage.ply", "not a ply at all\n");
  ExpectRefused("--ply " + dir_ + "/garbage.ply --camera " + camera_, 2, "garbage.ply");

  const std::string good =
      R"("fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5, "T_world_from_cam": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1])";
  const std::pair<std::string, std::string> cases[] = {
      {"{", "does not parse"},
      {"[1,2,3]", "must be an object"},
      {R"({"width": 320, )" + good + "}", "missing \"height\""},
      {R"({"width": 0, "height": 240, )" + good + "}", "positive integer"},
      {R"({"width": 320.5, "height": 240, )" + good + "}", "positive integer"},
      {R"({"width": 5000, "height": 240, )" + good + "}", "outside 1..4096"},
      {R"({"width": 320, "height": 240, "fx": -1, "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]})", "focal length"},
      {R"({"width": 320, "height": 240, "fx": "300", "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]})", "must be a number"},
      {R"({"width": 320, "height": 240, "fx": 300, "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [1,0,0]})", "16 numbers"},
      {R"({"width": 320, "height": 240, "fx": 300, "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [2,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]})", "orthonormal"},
      {R"({"width": 320, "height": 240, "fx": 300, "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,2]})", "bottom row"},
      {R"({"width": 320, "height": 240, "fx": 1e400, "fy": 300, "cx": 1, "cy": 1, "T_world_from_cam": [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]})", "camera"},
      {R"({"width": 320, "height": 240, "zoom": 2, )" + good + "}", "unknown camera field \"zoom\""},
  };
  for (const auto& [json, needle] : cases) {
    WriteFile(dir_ + "/bad.json", json);
    ExpectRefused("--ply " + kPly + " --camera " + dir_ + "/bad.json", 2, needle);
  }
  // A trained scene directory whose train_meta.json (the learned sky colour) is damaged.
  fs::create_directories(dir_ + "/scene");
  fs::copy_file(kPly, dir_ + "/scene/scene.ply");
  WriteFile(dir_ + "/scene/train_meta.json", "{\"background\": [0.5, ");
  ExpectRefused("--scene " + dir_ + "/scene --camera " + camera_, 2, "train_meta.json");
}

TEST_F(CliRender, RefusesUnwritableOutputsWithoutPartialFiles) {
  const std::string base = "render --ply " + kPly + " --camera " + camera_;
  ProcessResult r = Exec(base + " --out-rgb " + dir_ + "/no/such/dir/out.png");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.stderr_text.find("does not exist"), std::string::npos) << r.stderr_text;
  fs::create_directories(dir_ + "/adir.png");
  r = Exec(base + " --out-rgb " + dir_ + "/adir.png");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_NE(r.stderr_text.find("is a directory"), std::string::npos) << r.stderr_text;
  for (const auto& entry : fs::directory_iterator(dir_)) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp"), std::string::npos) << entry.path();
  }
}

}  // namespace
}  // namespace streetsim
