// `streetsim eval --decomposition DIR --video PATH` on a small trained KITTI field scene (its field
// given a moving band, so that some Gaussians are dynamic) and on the same scene without its
// field; the flags' bad values.
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "scene/field/field_io.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/ply_io.h"
#include "tests/common/cli_runner.h"
#include "tests/field/field_test_util.h"

namespace {

namespace fs = std::filesystem;
using namespace streetsim;

using streetsim::cli_test::kKitti;
using streetsim::cli_test::Result;
using streetsim::cli_test::RunStreetsim;
using streetsim::cli_test::Slurp;

const std::string kEvalArgs = " --log " + kKitti + " --no-lidar --resolution-scale 0.12 --holdout-every 10";

std::string TestDir(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("streetsim_cli_eval_outputs_" + std::to_string(getpid()) + "_" + name);
  fs::remove_all(d);
  fs::create_directories(d);
  return d.string();
}

Result RunCli(const std::string& args, const std::string& dir) {
  const std::string out = dir + "/stdout.txt", err = dir + "/stderr.txt";
  return RunStreetsim(args, out, err);
}

// The trained field's finest xt plane made to vary in time over its middle columns: the
// Gaussians in that x band move (cf. tests/field/static_skip_test.cc).
void AddMovingBand(const std::string& field_path) {
  absl::StatusOr<field::DeformationField> f = field::LoadField(field_path);
  ASSERT_TRUE(f.ok()) << f.status();
  field::testing::AddTimeVaryingBand(&*f, 2);
  ASSERT_TRUE(field::SaveField(*f, field_path).ok());
}

struct VideoInfo {
  int frames = 0, width = 0, height = 0;
};
VideoInfo ReadVideo(const std::string& path) {
  VideoInfo info;
  cv::VideoCapture cap(path);
  cv::Mat f;
  while (cap.read(f)) {
    ++info.frames;
    info.width = f.cols;
    info.height = f.rows;
  }
  return info;
}

// Shared by the tests: a 16-iteration s3gaussian run (about 5 s), trained once.
class CliEvalOutputs : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    root_ = new std::string(TestDir("suite"));
    scene_ = new std::string(*root_ + "/scene");
    const Result r = RunCli("train --log " + kKitti + " --out " + *scene_ +
                                // spec init: AddMovingBand's plane change must reach Δx through heads that
                                // 8 fine iterations have not yet grown from zero.
                                " --iterations 16 --field s3gaussian --static-iterations 8 --field-size small --field-motion-prior 0"
                                " --field-init spec --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3 --checkpoint-every 0",
                            *root_);
    ASSERT_EQ(r.code, 0) << r.err;
    AddMovingBand(*scene_ + "/field.bin");
  }
  static void TearDownTestSuite() {
    fs::remove_all(*root_);
    delete root_;
    delete scene_;
  }
  static std::string* root_;
  static std::string* scene_;
};
std::string* CliEvalOutputs::root_ = nullptr;
std::string* CliEvalOutputs::scene_ = nullptr;

TEST_F(CliEvalOutputs, FieldSceneWritesDecompositionAndVideo) {
  const std::string out = TestDir("field");
  const Result plain = RunCli("eval --scene " + *scene_ + kEvalArgs, out);
  ASSERT_EQ(plain.code, 0) << plain.err;
  const Result r = RunCli("eval --scene " + *scene_ + kEvalArgs + " --decomposition " + out +
                              "/dec/nested --video " + out + "/eval.avi --video-fps 4",
                          out);
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json j = nlohmann::json::parse(r.out);
  // Additive: the metrics are those of a plain eval.
  EXPECT_EQ(j["mean"], nlohmann::json::parse(plain.out)["mean"]);
  EXPECT_EQ(j["frames"], nlohmann::json::parse(plain.out)["frames"]);

  // The counts are the server's analysis of scene.ply with field.bin.
  absl::StatusOr<GaussianStore> g = ReadGaussianPly(*scene_ + "/scene.ply");
  ASSERT_TRUE(g.ok());
  absl::StatusOr<field::DeformationField> f = field::LoadField(*scene_ + "/field.bin");
  ASSERT_TRUE(f.ok());
  ThreadPool pool(2);
  absl::StatusOr<field::StaticAnalysis> a = field::AnalyseStatic(*f, *g, field::StaticSkipOptions{}, pool);
  ASSERT_TRUE(a.ok());
  const nlohmann::json& d = j["decomposition"];
  ASSERT_TRUE(d.is_object()) << r.out;
  EXPECT_EQ(d["has_field"], true);
  EXPECT_EQ(d["dynamic_gaussians"].get<size_t>(), a->dynamic_rows.size());
  EXPECT_EQ(d["static_gaussians"].get<size_t>() + d["dynamic_gaussians"].get<size_t>(), g->size());
  EXPECT_GT(d["dynamic_gaussians"].get<size_t>(), 0u);
  EXPECT_GT(d["static_gaussians"].get<size_t>(), 0u);
  EXPECT_FALSE(d.contains("note"));

  // One set of PNGs per evaluated view.
  const size_t views = j["frames"].size();
  ASSERT_GT(views, 2u);
  EXPECT_EQ(d["views"].get<size_t>(), views);
  cv::Mat full;
  for (const nlohmann::json& fr : j["frames"]) {
    std::string stem = fr["name"].get<std::string>();
    std::replace(stem.begin(), stem.end(), '/', '_');
    stem = out + "/dec/nested/" + stem.substr(0, stem.rfind('.'));
    full = cv::imread(stem + "_full.png");
    ASSERT_FALSE(full.empty()) << stem;
    for (const char* s : {"_static.png", "_dynamic.png"}) {
      const cv::Mat m = cv::imread(stem + s);
      EXPECT_EQ(m.size(), full.size()) << stem << s;
    }
  }

  // The video: one frame per view, rendered | ground truth | dynamic only (even-padded).
  const nlohmann::json& v = j["video"];
  ASSERT_TRUE(v.is_object()) << r.out;
  EXPECT_EQ(v["frames"].get<size_t>(), views);
  EXPECT_EQ(v["fps"].get<double>(), 4.0);
  const VideoInfo info = ReadVideo(out + "/eval.avi");
  EXPECT_EQ(info.frames, static_cast<int>(views));
  EXPECT_EQ(info.width, (3 * full.cols + 1) / 2 * 2);
  EXPECT_EQ(info.height, (full.rows + 1) / 2 * 2);
  EXPECT_EQ(v["width"].get<int>(), info.width);
  fs::remove_all(out);
}

TEST_F(CliEvalOutputs, StaticSceneIsAllStaticAndItsVideoHasTwoPanels) {
  const std::string out = TestDir("static");
  const std::string scene = out + "/scene";
  fs::create_directories(scene);
  for (const char* f : {"scene.ply", "train_meta.json"}) fs::copy_file(*scene_ + "/" + f, scene + "/" + f);
  const Result r = RunCli("eval --scene " + scene + kEvalArgs + " --decomposition " + out + "/dec --video " + out +
                              "/eval.mp4",
                          out);
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json j = nlohmann::json::parse(r.out);
  const nlohmann::json& d = j["decomposition"];
  EXPECT_EQ(d["has_field"], false);
  EXPECT_EQ(d["dynamic_gaussians"], 0);
  EXPECT_GT(d["static_gaussians"].get<size_t>(), 0u);
  EXPECT_TRUE(d["note"].is_string());
  const std::string stem = out + "/dec/image_02_0000000009";
  const cv::Mat full = cv::imread(stem + "_full.png"), stat = cv::imread(stem + "_static.png");
  ASSERT_FALSE(full.empty());
  EXPECT_EQ(cv::norm(full, stat, cv::NORM_INF), 0.0);  // every Gaussian is static
  EXPECT_EQ(cv::countNonZero(cv::imread(stem + "_dynamic.png", cv::IMREAD_GRAYSCALE)), 0);
  const VideoInfo info = ReadVideo(out + "/eval.mp4");
  EXPECT_EQ(info.frames, static_cast<int>(j["frames"].size()));
  EXPECT_EQ(info.width, (2 * full.cols + 1) / 2 * 2);
  fs::remove_all(out);
}

// Checked before anything is loaded: no scene needed (the message names the flag at fault).
TEST(CliEvalOutputsArgs, BadValuesExitTwoWithOneLineAndWriteNothing) {
  const std::string out = TestDir("bad");
  const std::string eval = "eval --scene " + out + "/no_scene" + kEvalArgs;
  fs::create_directories(out + "/file_parent");
  std::ofstream(out + "/a_file") << "x";
  for (const std::string& args : {
           eval + " --video " + out + "/no/such/dir/v.avi",
           eval + " --video " + out + "/v.mkv",
           eval + " --video " + out + "/file_parent",
           eval + " --video-fps 5",
           eval + " --video " + out + "/v.avi --video-fps 0",
           eval + " --video " + out + "/v.avi --video-fps fast",
           eval + " --decomposition " + out + "/a_file/sub",
       }) {
    const Result r = RunCli(args, out);
    EXPECT_EQ(r.code, 2) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
    EXPECT_TRUE(r.out.empty()) << args;
    EXPECT_TRUE(r.err.find("--video") != std::string::npos || r.err.find("--decomposition") != std::string::npos)
        << args << ": " << r.err;
  }
  EXPECT_FALSE(fs::exists(out + "/v.avi"));
  EXPECT_FALSE(fs::exists(out + "/v.mkv"));
  fs::remove_all(out);
}

}  // namespace
