// streetsim train / eval from the command line: exit codes, outputs, and eval's JSON contract
// ({"mean": {"psnr", "ssim", ...}, "frames": [...]}).
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"
#include "tests/common/scratch_dir.h"

namespace {

const std::string kBinary = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
const std::string kKitti = std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

struct Result {
  int code;
  std::string out, err;
};

Result RunCli(const std::string& args) {
  const auto dir = std::filesystem::temp_directory_path();
  const std::string out = (dir / ("streetsim_cli_train_out." + std::to_string(getpid()) + ".txt")).string();
  const std::string err = (dir / ("streetsim_cli_train_err." + std::to_string(getpid()) + ".txt")).string();
  const int status = std::system((kBinary + " " + streetsim::cli_test::WithoutActorsUnlessNamed(args) + " >" + out + " 2>" + err).c_str());
  auto slurp = [](const std::string& p) {
    std::ifstream f(p);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
  };
  Result r{WEXITSTATUS(status), slurp(out), slurp(err)};
  std::filesystem::remove(out);
  std::filesystem::remove(err);
  return r;
}

TEST(CliTrain, TrainThenEvalGivesTheJsonContract) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "run");
  Result r = RunCli("train --log " + kKitti + " --out " + dir +
                 " --iterations 20 --resolution-scale 0.12 --holdout-every 4 --seed 3 --checkpoint-every 10");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("20/20"), std::string::npos);
  EXPECT_NE(r.err.find("Gaussians"), std::string::npos);
  for (const char* f : {"scene.ply", "checkpoint.bin", "curve.png", "train_meta.json"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + f)) << f;
  }
  // --resume of a finished run: nothing left to do, same outputs.
  r = RunCli("train --log " + kKitti + " --out " + dir + " --iterations 20 --resolution-scale 0.12 --resume");
  EXPECT_EQ(r.code, 0) << r.err;

  r = RunCli("eval --scene " + dir + " --log " + kKitti + " --split test --holdout-every 4");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json j = nlohmann::json::parse(r.out);
  ASSERT_TRUE(j.contains("mean"));
  ASSERT_TRUE(j.contains("frames"));
  EXPECT_TRUE(j["mean"]["psnr"].is_number());
  EXPECT_TRUE(j["mean"]["ssim"].is_number());
  EXPECT_TRUE(j["mean"].contains("depth_median_abs_m"));
  EXPECT_TRUE(j["mean"].contains("depth_within_5pct"));
  EXPECT_EQ(j["frames"].size(), 19u);  // frames 3, 7, ..., 75 of 78
  EXPECT_EQ(j["frames"][0]["frame"], 3);
  EXPECT_NE(r.err.find("mean"), std::string::npos);  // the table
  // The run left the same held-out metrics beside its scene (DIR/heldout.json, one schema with
  // eval's; the server's job record reads it).
  const nlohmann::json heldout = nlohmann::json::parse(std::ifstream(dir + "/heldout.json"));
  EXPECT_EQ(heldout["views"], 19);
  ASSERT_EQ(heldout["frames"].size(), 19u);
  EXPECT_EQ(heldout["frames"][0]["frame"], 3);
  EXPECT_NEAR(heldout["mean"]["psnr"].get<double>(), j["mean"]["psnr"].get<double>(), 0.01);
  EXPECT_NEAR(heldout["mean"]["ssim"].get<double>(), j["mean"]["ssim"].get<double>(), 1e-4);

  // `render --scene DIR` composites over the sky colour the run learned (as eval and the server
  // do): default render minus a render on black = (1 - alpha) x sky, pixel by pixel.
  const nlohmann::json meta = nlohmann::json::parse(std::ifstream(dir + "/train_meta.json"));
  const cv::Vec3f sky_bgr(meta["background"][2].get<float>(), meta["background"][1].get<float>(),
                          meta["background"][0].get<float>());
  ASSERT_GT(std::max({sky_bgr[0], sky_bgr[1], sky_bgr[2]}), 0.05f) << meta.dump();
  ASSERT_EQ(RunCli("log camera " + kKitti + " --frame 3 --out " + dir + "/cam3.json").code, 0);
  const std::string view = "render --scene " + dir + " --time-us 300000 --camera " + dir + "/cam3.json --out-rgb ";
  r = RunCli(view + dir + "/sky.png --out-alpha " + dir + "/alpha.tiff");
  ASSERT_EQ(r.code, 0) << r.err;
  ASSERT_EQ(RunCli(view + dir + "/black.png --background 0,0,0").code, 0);
  const cv::Mat sky = cv::imread(dir + "/sky.png"), black = cv::imread(dir + "/black.png");
  const cv::Mat alpha = cv::imread(dir + "/alpha.tiff", cv::IMREAD_UNCHANGED);
  ASSERT_FALSE(sky.empty());
  ASSERT_EQ(sky.size(), black.size());
  ASSERT_EQ(alpha.size(), sky.size());
  int compared = 0, off = 0;
  for (int y = 0; y < sky.rows; ++y) {
    for (int x = 0; x < sky.cols; ++x) {
      const float t = 1.0f - alpha.at<float>(y, x);
      for (int c = 0; c < 3; ++c) {
        if (sky.at<cv::Vec3b>(y, x)[c] == 255) continue;  // clamped
        ++compared;
        const float got = float(sky.at<cv::Vec3b>(y, x)[c]) - float(black.at<cv::Vec3b>(y, x)[c]);
        off += std::abs(got - 255.0f * t * sky_bgr[c]) > 1.01f;
      }
    }
  }
  EXPECT_GT(compared, sky.rows * sky.cols);
  EXPECT_EQ(off, 0) << "of " << compared;
}

// The run's last stage (docs/actors.md): the log's moving objects become actors beside the scene;
// `actors list` reads them, a resume with nothing to do keeps them, and a run without them leaves
// none of an earlier scene behind.
TEST(CliTrain, ActorsAtTheEndOfTheRun) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "actors");
  const std::string run = "train --log " + kKitti + " --out " + dir +
                          " --iterations 10 --resolution-scale 0.12 --holdout-every 4 --field-motion-prior 0";
  Result r = RunCli(run + " --actors");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find(" actors ("), std::string::npos) << r.err;
  r = RunCli("actors list --scene " + dir + " --json");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json list = nlohmann::json::parse(r.out);
  // The clip's moving vehicles: the tanker, the cars behind and across (docs/actors.md).
  EXPECT_GE(list["actors"].size(), 3u) << r.out;
  for (const auto& a : list["actors"]) {
    EXPECT_GT(a["half_extent_m"][0].get<double>(), 0.3);
    EXPECT_LE(a["start_time_us"].get<int64_t>(), a["end_time_us"].get<int64_t>());
  }
  const auto written = std::filesystem::last_write_time(dir + "/actors.json");
  r = RunCli(run + " --actors --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(std::filesystem::last_write_time(dir + "/actors.json"), written) << "nothing changed: kept";
  r = RunCli(run + " --no-actors");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(dir + "/actors.json"));
  EXPECT_EQ(RunCli("actors list --scene " + dir).code, 2);
  EXPECT_EQ(RunCli("actors extract --scene /nonexistent --log " + kKitti).code, 2);
  EXPECT_EQ(RunCli("actors extract --scene " + dir).code, 2) << "--log is required";
  EXPECT_EQ(RunCli("actors bogus").code, 2);
}

TEST(CliTrain, BadArgumentsExitTwoWithOneLine) {
  for (const std::string& args :
       {std::string("train --out /tmp/x"), "train --log " + kKitti + " --out /tmp/x --iterations 0",
        "train --log " + kKitti + " --out /tmp/x --resolution-scale 2",
        "train --log " + kKitti + " --out /tmp/x --holdout-every -1", std::string("train --log /nonexistent --out /tmp/x"),
        "eval --scene /nonexistent --log " + kKitti, "eval --scene /tmp --log " + kKitti + " --split bogus",
        // Low resolution first: both flags (or --low-res-iterations 0 alone), a scale below the
        // run's, a stage shorter than the run.
        "train --log " + kKitti + " --out /tmp/x --low-res-scale 0.25",
        "train --log " + kKitti + " --out /tmp/x --low-res-scale 1 --low-res-iterations 5",
        "train --log " + kKitti + " --out /tmp/x --resolution-scale 0.5 --low-res-scale 0.5 --low-res-iterations 5",
        "train --log " + kKitti + " --out /tmp/x --low-res-scale nan --low-res-iterations 5",
        "train --log " + kKitti + " --out /tmp/x --low-res-scale 0.25 --low-res-iterations -3",
        "train --log " + kKitti + " --out /tmp/x --low-res-scale 0.25 --low-res-iterations 0",
        "train --log " + kKitti + " --out /tmp/x --iterations 10 --low-res-scale 0.25 --low-res-iterations 10",
        // Pose refinement's options need it; its rate scale is positive.
        "train --log " + kKitti + " --out /tmp/x --no-pose-refinement --pose-lr-scale 2",
        "train --log " + kKitti + " --out /tmp/x --no-pose-refinement --pose-refine-from 2",
        "train --log " + kKitti + " --out /tmp/x --pose-refinement --pose-lr-scale 0",
        "train --log " + kKitti + " --out /tmp/x --pose-refinement --pose-refine-from -1",
        "train --log " + kKitti + " --out /tmp/x --no-pose-refinement --pose-refine-until 5",
        "train --log " + kKitti + " --out /tmp/x --pose-refinement --pose-refine-until -2",
        // Settings by name, presets and config files (issue 34).
        "train --log " + kKitti + " --out /tmp/x --set warp=1",
        "train --log " + kKitti + " --out /tmp/x --set iterations=many",
        "train --log " + kKitti + " --out /tmp/x --set iterations",
        "train --log " + kKitti + " --out /tmp/x --preset fastest",
        "train --log " + kKitti + " --out /tmp/x --config /nonexistent/run.json"}) {
    const Result r = RunCli(args);
    EXPECT_EQ(r.code, 2) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
  }
}

// Camera pose refinement (docs/training.md): the run writes its corrections, its held-out metrics
// are at the interpolated corrections as eval's are, --log-poses measures at the log's, a resume
// keeps refining, and a new run without refinement in the same directory removes the file.
TEST(CliTrain, PoseRefinementWritesCorrectionsThatEvalUses) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "poses");
  const std::string common = " --log " + kKitti + " --out " + dir + " --resolution-scale 0.12 --holdout-every 4";
  Result r = RunCli("train" + common + " --iterations 30 --pose-refinement --pose-refine-from 5 --pose-lr-scale 2");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("pose corrections: 59 views"), std::string::npos) << r.err;
  const nlohmann::json c = nlohmann::json::parse(std::ifstream(dir + "/pose_corrections.json"));
  ASSERT_EQ(c["corrections"].size(), 59u);  // 78 frames, every 4th held out
  // 25 refined iterations, one view each: some views moved, none far.
  int moved = 0;
  for (const auto& e : c["corrections"]) moved += e["rotation_rad"][0].get<double>() != 0;
  EXPECT_GE(moved, 10);
  EXPECT_LT(c["max_rotation_deg"].get<double>(), 1.0);
  EXPECT_GT(c["max_rotation_deg"].get<double>(), 0.0);
  EXPECT_LT(c["max_translation_m"].get<double>(), 0.1);

  const std::string eval = "eval --scene " + dir + " --log " + kKitti + " --split test --holdout-every 4 --no-lidar";
  r = RunCli(eval);
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json corrected = nlohmann::json::parse(r.out);
  EXPECT_EQ(corrected["poses"], "corrected");
  const nlohmann::json heldout = nlohmann::json::parse(std::ifstream(dir + "/heldout.json"));
  EXPECT_NEAR(heldout["mean"]["psnr"].get<double>(), corrected["mean"]["psnr"].get<double>(), 0.01);
  r = RunCli(eval + " --log-poses");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json logged = nlohmann::json::parse(r.out);
  EXPECT_EQ(logged["poses"], "log");
  EXPECT_NE(logged["mean"]["psnr"].get<double>(), corrected["mean"]["psnr"].get<double>());

  // A damaged corrections file is an error, not a silent evaluation at other poses.
  std::ofstream(dir + "/pose_corrections.json") << "{\"corrections\": [1]}";
  r = RunCli(eval);
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("pose_corrections.json"), std::string::npos) << r.err;

  // A resume goes on refining (its scene sits in the corrected frame); a new run in the same
  // directory without refinement leaves no stale corrections behind.
  r = RunCli("train" + common + " --iterations 31 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(dir + "/pose_corrections.json"))["corrections"].size(), 59u);
  const nlohmann::json settings = nlohmann::json::parse(std::ifstream(dir + "/config.json"))["settings"];
  EXPECT_DOUBLE_EQ(settings["pose-lr-scale"].get<double>(), 2);  // its own schedule, kept
  EXPECT_EQ(settings["pose-refine-from"], 5);
  // checkpoint.json holds the checkpoint's state, not the settings (config.json has them).
  const nlohmann::json run = nlohmann::json::parse(std::ifstream(dir + "/checkpoint.json"));
  EXPECT_FALSE(run.contains("pose_refine_from")) << run.dump();
  // So does one from before config.json whose checkpoint.json predates the record of the
  // schedule (migrated: the checkpoint's corrections carry on).
  std::filesystem::remove(dir + "/config.json");
  r = RunCli("train" + common + " --iterations 32 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("predates config.json"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("the checkpoint refines its camera poses"), std::string::npos) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(dir + "/pose_corrections.json"))["corrections"].size(), 59u);
  // A damaged config is an error naming the file, not a run on some other schedule.
  std::ofstream(dir + "/config.json", std::ios::trunc) << R"({"schema_version": 1, "settings": {"pose-refine-from": -4}})";
  r = RunCli("train" + common + " --iterations 33 --resume");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("config.json: pose-refine-from must be an integer in 0..10000000, not '-4'"), std::string::npos)
      << r.err;
  r = RunCli("train" + common + " --iterations 5 --no-pose-refinement");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(dir + "/pose_corrections.json"));
}

// --pose-refine-until M: the corrections stop at iteration M. Deterministic runs: 12 iterations
// with corrections until 8 end with the corrections of an 8-iteration run, and so does a run
// resumed without the flags.
TEST(CliTrain, PoseRefinementStopsAtItsLastIteration) {
  const std::string a = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "poses_until");
  const std::string b = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "poses_8");
  const std::string common = " --log " + kKitti +
                             " --resolution-scale 0.08 --holdout-every 4 --deterministic --no-lidar-loss"
                             " --pose-refinement --pose-refine-from 2 --pose-lr-scale 2";
  Result r = RunCli("train --out " + a + common + " --iterations 12 --pose-refine-until 8");
  ASSERT_EQ(r.code, 0) << r.err;
  r = RunCli("train --out " + b + common + " --iterations 8");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json ca = nlohmann::json::parse(std::ifstream(a + "/pose_corrections.json"));
  const nlohmann::json cb = nlohmann::json::parse(std::ifstream(b + "/pose_corrections.json"));
  EXPECT_GT(cb["max_rotation_deg"].get<double>(), 0.0);
  EXPECT_EQ(ca["corrections"], cb["corrections"]);

  // A resume without the pose flags keeps the run's schedule (config.json records it): 6
  // iterations, then resumed to 12 with none of the flags, end where the 8-iteration run ended.
  // The defaults instead (rates halved, refinement from 300, never frozen) would not.
  const std::string c = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "poses_resumed");
  const std::string plain =
      " --log " + kKitti + " --resolution-scale 0.08 --holdout-every 4 --deterministic --no-lidar-loss";
  r = RunCli("train --out " + c + common + " --iterations 6 --pose-refine-until 8");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json settings = nlohmann::json::parse(std::ifstream(c + "/config.json"))["settings"];
  EXPECT_EQ(settings["pose-refine-from"], 2);
  EXPECT_EQ(settings["pose-refine-until"], 8);
  EXPECT_DOUBLE_EQ(settings["pose-lr-scale"].get<double>(), 2);
  r = RunCli("train --out " + c + plain + " --iterations 12 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(c + "/pose_corrections.json"))["corrections"], cb["corrections"]);
  // Told otherwise, it does: --pose-refine-until 14 alone (no --pose-refinement needed on a run that
  // refines) sets them moving again.
  r = RunCli("train --out " + c + plain + " --iterations 14 --resume --pose-refine-until 14");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(nlohmann::json::parse(std::ifstream(c + "/pose_corrections.json"))["corrections"], cb["corrections"]);

  // A field run freezes them at the end of its static stage unless told otherwise.
  const std::string f = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "poses_field");
  r = RunCli("train --out " + f + common +
             " --iterations 8 --field s3gaussian --field-size small --field-motion-prior 0 --static-iterations 6 --checkpoint-every 0");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("camera poses refined at iterations 3-6"), std::string::npos) << r.err;
  r = RunCli("train --out " + f + common +
             " --iterations 8 --field s3gaussian --field-size small --field-motion-prior 0 --static-iterations 6 --checkpoint-every 0"
             " --pose-refine-until 7");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(f + "/config.json"))["settings"]["pose-refine-until"], 7);
}

// --position-lr-decay-iterations N: the Gaussian means' rate decays over N iterations instead of
// 3DGS's 30 000. Deterministic runs: the flag changes the trained scene; config.json records
// it; a resume without the flag keeps it (ends bit for bit where the uninterrupted run ended), and
// a damaged record or a bad value is exit 2.
TEST(CliTrain, PositionLrDecayIsTheRunsAndAResumeKeepsIt) {
  const std::string a = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "xyz_decay");
  const std::string b = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "xyz_default");
  const std::string c = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "xyz_resumed");
  const std::string common =
      " --log " + kKitti + " --resolution-scale 0.08 --holdout-every 4 --deterministic --no-lidar-loss --seed 1";
  auto slurp = [](const std::string& p) {
    std::ifstream f(p, std::ios::binary);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
  };
  Result r = RunCli("train --out " + a + common + " --iterations 10 --position-lr-decay-iterations 3");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(a + "/config.json"))["settings"]["position-lr-decay-iterations"], 3);
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(a + "/train_meta.json"))["position_lr_decay_iterations"], 3);
  r = RunCli("train --out " + b + common + " --iterations 10");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(b + "/train_meta.json"))["position_lr_decay_iterations"], 30000);
  EXPECT_NE(slurp(a + "/scene.ply"), slurp(b + "/scene.ply"));

  r = RunCli("train --out " + c + common + " --iterations 6 --position-lr-decay-iterations 3");
  ASSERT_EQ(r.code, 0) << r.err;
  r = RunCli("train --out " + c + common + " --iterations 10 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(slurp(c + "/scene.ply"), slurp(a + "/scene.ply"));
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(c + "/train_meta.json"))["position_lr_decay_iterations"], 3);

  EXPECT_EQ(nlohmann::json::parse(std::ifstream(c + "/config.json"))["settings"]["position-lr-decay-iterations"], 3);
  r = RunCli("train --out " + c + common + " --iterations 12 --resume --position-lr-decay-iterations 0");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("--position-lr-decay-iterations: position-lr-decay-iterations must be an integer in "
                       "1..10000000, not '0'"),
            std::string::npos)
      << r.err;
}

// --densify-until N: config.json and train_meta.json record it, a resume without the flag
// keeps it and one with the flag replaces it; a damaged record or a bad value is exit 2. (What it
// does to the Gaussians: tests/train/trainer_test.cc, Trainer.DensifyUntilEndsDensificationAndResets.)
TEST(CliTrain, DensifyUntilIsRecordedAndKeptByAResume) {
  const std::string a = streetsim::testing::ScratchDir("streetsim_cli_train_scene", "densify_until");
  const std::string common =
      " --log " + kKitti + " --out " + a + " --resolution-scale 0.08 --holdout-every 4 --no-lidar-loss --seed 1";
  auto recorded = [&](const std::string& file) { return nlohmann::json::parse(std::ifstream(a + "/" + file)); };
  Result r = RunCli("train" + common + " --iterations 4");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(recorded("train_meta.json")["densify_until"], 25000);
  r = RunCli("train" + common + " --iterations 6 --resume --densify-until 0");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(recorded("train_meta.json")["densify_until"], 0);
  r = RunCli("train" + common + " --iterations 8 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(recorded("train_meta.json")["densify_until"], 0);
  EXPECT_EQ(recorded("train_meta.json")["iterations"], 8);

  // config.json records where the change began: the run's schedule has a stage from iteration 4.
  const nlohmann::json config = recorded("config.json");
  EXPECT_EQ(config["schedule"][1]["from"], 4) << config.dump();
  EXPECT_EQ(config["schedule"][1]["set"]["densify-until"], 0) << config.dump();
  // A damaged or future config.json is refused, naming the file.
  std::ofstream(a + "/config.json", std::ios::trunc) << config.dump().substr(0, 40);
  r = RunCli("train" + common + " --iterations 10 --resume");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find(a + "/config.json is not valid JSON (damaged)"), std::string::npos) << r.err;
  nlohmann::json future = config;
  future["schema_version"] = 2;
  std::ofstream(a + "/config.json", std::ios::trunc) << future.dump();
  r = RunCli("train" + common + " --iterations 10 --resume");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("has schema_version 2, newer than this streetsim's 1"), std::string::npos) << r.err;
  std::ofstream(a + "/config.json", std::ios::trunc) << config.dump();
  for (const char* bad : {"-1", "many", "10000001"}) {
    r = RunCli("train" + common + " --iterations 10 --resume --densify-until " + bad);
    EXPECT_EQ(r.code, 2) << r.err;
    EXPECT_NE(r.err.find("densify-until must be an integer in 0..10000000, not '" + std::string(bad) + "'"),
              std::string::npos)
        << r.err;
  }
}

// Low resolution first (docs/training.md "Low resolution first"): the first iterations at the low
// scale, fine stage included, then the rest resumed at the run's; the outputs are the run's
// resolution; a resume keeps the stage config.json records unless told otherwise.
TEST(CliTrain, LowResolutionFirstThenTheRunsOwn) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_lowres", "run");
  const std::string common = "train --log " + kKitti + " --out " + dir +
                             " --holdout-every 10 --voxel 0.5 --seed 3 --field s3gaussian"
                             " --field-size small --field-motion-prior 0 --static-iterations 4 --checkpoint-every 0";
  Result r = RunCli(common + " --resolution-scale 0.12 --iterations 10 --low-res-scale 0.06 --low-res-iterations 7");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("low-resolution stage: iterations 1-7 at resolution scale 0.06, then 8-10 at 0.12"),
            std::string::npos) << r.err;
  EXPECT_NE(r.err.find("resumed from " + dir + "/checkpoint.bin at iteration 7"), std::string::npos) << r.err;
  auto progress_line = [&](const std::string& it) {
    const size_t at = r.err.find("] " + it + " ");
    return at == std::string::npos ? std::string() : r.err.substr(at, r.err.find('\n', at) - at);
  };
  EXPECT_NE(progress_line("7/10").find("(low-resolution stage at scale 0.06)"), std::string::npos) << r.err;
  EXPECT_EQ(progress_line("10/10").find("low-resolution"), std::string::npos) << r.err;
  EXPECT_FALSE(progress_line("10/10").empty()) << r.err;
  EXPECT_NE(r.err.find("held-out ("), std::string::npos) << r.err;
  nlohmann::json meta = nlohmann::json::parse(std::ifstream(dir + "/train_meta.json"));
  EXPECT_DOUBLE_EQ(meta["resolution_scale"].get<double>(), 0.12);
  EXPECT_DOUBLE_EQ(meta["low_res_scale"].get<double>(), 0.06);
  EXPECT_EQ(meta["low_res_iterations"], 7);
  EXPECT_EQ(meta["field"], "s3gaussian");  // the field began at low resolution and carried on
  EXPECT_TRUE(std::filesystem::exists(dir + "/field.bin"));
  const nlohmann::json settings = nlohmann::json::parse(std::ifstream(dir + "/config.json"))["settings"];
  EXPECT_DOUBLE_EQ(settings["low-res-scale"].get<double>(), 0.06);
  EXPECT_EQ(settings["low-res-iterations"], 7);
  // The previews (render | ground truth) are at the run's scale: 375 rows x 0.12.
  int previews = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir + "/preview")) {
    const cv::Mat p = cv::imread(e.path().string());
    EXPECT_NEAR(p.rows, 45, 1) << e.path();
    ++previews;
  }
  EXPECT_GT(previews, 0);

  // A resume past the switch keeps the recorded stage (for the record) and trains at 0.12.
  r = RunCli(common + " --resolution-scale 0.12 --iterations 12 --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err.find("low-resolution stage:"), std::string::npos) << r.err;
  meta = nlohmann::json::parse(std::ifstream(dir + "/train_meta.json"));
  EXPECT_EQ(meta["iterations"], 12);
  EXPECT_EQ(meta["low_res_iterations"], 7);
  // A recorded stage that does not fit the resumed run's flags is refused, with the way out.
  r = RunCli(common + " --iterations 13 --resume --resolution-scale 0.05");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("(low-res-iterations 0: none)"), std::string::npos) << r.err;
  r = RunCli(common + " --iterations 13 --resume --resolution-scale 0.05 --low-res-iterations 0");
  ASSERT_EQ(r.code, 0) << r.err;
  meta = nlohmann::json::parse(std::ifstream(dir + "/train_meta.json"));
  EXPECT_FALSE(meta.contains("low_res_scale")) << meta.dump();
  EXPECT_DOUBLE_EQ(meta["resolution_scale"].get<double>(), 0.05);
  // A damaged record is refused, naming the file.
  nlohmann::json damaged = nlohmann::json::parse(std::ifstream(dir + "/config.json"));
  damaged["settings"]["low-res-scale"] = -1;
  std::ofstream(dir + "/config.json", std::ios::trunc) << damaged.dump();
  r = RunCli(common + " --resolution-scale 0.05 --iterations 14 --resume");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("config.json: low-res-scale must be a number in (0, 1], not '-1'"), std::string::npos)
      << r.err;
}

}  // namespace

namespace {

// `streetsim ARGS` started in the background; once its progress shows, signal `sig`; the exit
// code and stderr.
Result RunAndSignal(const std::string& args, const char* sig, const std::string& scratch) {
  const std::string err = scratch + "/err.txt", code = scratch + "/code.txt", script = scratch + "/run.sh";
  std::ofstream(script) << kBinary << " " << args << " >/dev/null 2>" << err << " & p=$!\n"
                        << "for i in $(seq 600); do grep -q 'it/s' " << err << " && break; sleep 0.05; done\n"
                        << "kill -" << sig << " $p; wait $p; echo $? >" << code << "\n";
  EXPECT_EQ(std::system(("bash " + script).c_str()), 0);
  std::ifstream c(code), e(err);
  int rc = -1;
  c >> rc;
  std::stringstream s;
  s << e.rdbuf();
  return Result{rc, "", s.str()};
}

}  // namespace

// Ctrl-C (or the job runner's SIGTERM) stops a run after the iteration in progress with a
// checkpoint, exit 128 + signal, one line saying where; --resume continues from that iteration.
TEST(CliTrain, ASignalStopsWithACheckpointThatResumes) {
  for (const char* sig : {"INT", "TERM"}) {
    const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_signal", sig);
    const std::string common = " --log " + kKitti + " --out " + dir +
                               " --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --no-lidar-loss --field static";
    const Result r = RunAndSignal("train --iterations 1000000" + common, sig, dir);
    EXPECT_EQ(r.code, std::string(sig) == "INT" ? 130 : 143) << r.err;
    EXPECT_NE(r.err.find("checkpoint written: --resume continues from it"), std::string::npos) << r.err;
    const nlohmann::json run = nlohmann::json::parse(std::ifstream(dir + "/checkpoint.json"));
    const int64_t stopped_at = run["iteration"].get<int64_t>();
    EXPECT_GE(stopped_at, 1);
    EXPECT_LT(stopped_at, 1000000);
    const Result resumed = RunCli("train --iterations " + std::to_string(stopped_at + 2) + " --resume" + common);
    EXPECT_EQ(resumed.code, 0) << resumed.err;
    EXPECT_NE(resumed.err.find("at iteration " + std::to_string(stopped_at)), std::string::npos) << resumed.err;
    EXPECT_TRUE(std::filesystem::exists(dir + "/scene.ply"));
  }
}

// Every command's --help / -h: its part of the usage, on stdout, exit 0 (also after other flags).
TEST(CliTrain, CommandHelpPrintsThatCommandsUsage) {
  for (const auto& [args, expect] : std::vector<std::pair<std::string, std::string>>{
           {"train --help", "streetsim train --log PATH --out DIR"},
           {"train --log x -h", "--preset NAME"},
           {"eval -h", "streetsim eval --scene DIR --log PATH"},
           {"serve --help", "streetsim serve"},
           {"log info --help", "streetsim log poses PATH"}}) {
    const Result r = RunCli(args);
    EXPECT_EQ(r.code, 0) << args << ": " << r.err;
    EXPECT_NE(r.out.find(expect), std::string::npos) << args << ": " << r.out;
    EXPECT_EQ(r.out.find("  render "), std::string::npos) << args << ": more than its own part";
  }
  EXPECT_EQ(RunCli("bogus --help").code, 2);
}

// The divergence guard (docs/training.md "Divergence guard"), driven by a run forced to diverge:
// absurd pose rates (x1000) set moving in the fine stage right after a checkpoint ruin the
// training views. Deterministic runs: the guarded run rolls back to that checkpoint twice,
// lowering the moving rates by 4 each time, says so in the log and config.json, and ends at
// pose rates x62.5 with a usable scene; the same run without the guard ends ruined.
TEST(CliTrain, ADivergingRunRollsBackAndLowersItsRates) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_train_diverge", "guarded");
  const std::string plain = streetsim::testing::ScratchDir("streetsim_cli_train_diverge", "unguarded");
  const std::string common = "train --log " + kKitti +
                             " --iterations 1000 --static-iterations 300 --resolution-scale 0.12 --voxel 0.5"
                             " --holdout-every 10 --checkpoint-every 600 --field-size small --field-motion-prior 0 --no-lidar-loss"
                             " --set field-motion-prior=0 --pose-refinement --pose-refine-until 0"
                             " --pose-refine-from 600 --pose-lr-scale 1000 --deterministic";
  Result r = RunCli(common + " --out " + dir);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("(fine stage): the training loss's running mean"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("rolled back to the checkpoint of iteration 600 with field-lr-scale 10 -> 2.5, "
                       "pose-lr-scale 1000 -> 250"),
            std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("rolled back to the checkpoint of iteration 600 with field-lr-scale 2.5 -> 0.625, "
                       "pose-lr-scale 250 -> 62.5"),
            std::string::npos)
      << r.err;
  EXPECT_EQ(nlohmann::json::parse(std::ifstream(dir + "/checkpoint.json"))["iteration"], 1000);
  const nlohmann::json config = nlohmann::json::parse(std::ifstream(dir + "/config.json"));
  ASSERT_EQ(config["notes"].size(), 2u) << config.dump();
  bool stage_at_600 = false;
  for (const auto& stage : config["schedule"]) {
    if (stage["from"] != 600) continue;
    stage_at_600 = true;
    EXPECT_DOUBLE_EQ(stage["set"]["field-lr-scale"].get<double>(), 0.625) << config.dump();
    EXPECT_DOUBLE_EQ(stage["set"]["pose-lr-scale"].get<double>(), 62.5) << config.dump();
  }
  EXPECT_TRUE(stage_at_600) << config.dump();
  const double guarded = nlohmann::json::parse(std::ifstream(dir + "/heldout.json"))["mean"]["psnr"].get<double>();

  r = RunCli(common + " --out " + plain + " --no-divergence-guard");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(r.err.find("rolled back"), std::string::npos) << r.err;
  const double unguarded = nlohmann::json::parse(std::ifstream(plain + "/heldout.json"))["mean"]["psnr"].get<double>();
  EXPECT_GT(guarded, unguarded + 3) << "guarded " << guarded << " dB, unguarded " << unguarded << " dB";
}

// A schedule in a --config file runs its stages in one process, each stage end writing the
// outputs as a run of that length would; deterministic runs: the same bytes as the two resumed
// runs it stands for. Each stage end adds to DIR/heldout_history.json and its plot.
TEST(CliTrain, AScheduleIsItsResumedSegmentsInOneRun) {
  const std::string one = streetsim::testing::ScratchDir("streetsim_cli_train_schedule", "one");
  const std::string two = streetsim::testing::ScratchDir("streetsim_cli_train_schedule", "two");
  const std::string config = one + "/../schedule.json";
  std::ofstream(config) << R"({"schema_version": 1, "settings": {"iterations": 16, "resolution-scale": 0.08,
      "holdout-every": 4, "seed": 2, "deterministic": true, "lidar-loss": false},
      "schedule": [{"from": 0}, {"from": 10, "set": {"position-lr-decay-iterations": 3}}]})";
  Result r = RunCli("train --log " + kKitti + " --out " + one + " --preset preview --config " + config);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("stage 1 of 2 ends at iteration 10: held-out PSNR"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("stage 2 of 2 ends at iteration 16"), std::string::npos) << r.err;
  const nlohmann::json history = nlohmann::json::parse(std::ifstream(one + "/heldout_history.json"));
  ASSERT_EQ(history["stages"].size(), 2u) << history.dump();
  EXPECT_EQ(history["stages"][0]["iteration"], 10);
  EXPECT_EQ(history["stages"][1]["iteration"], 16);
  EXPECT_GT(history["stages"][1]["seconds"].get<double>(), history["stages"][0]["seconds"].get<double>());
  EXPECT_TRUE(std::filesystem::exists(one + "/heldout_curve.png"));

  const std::string flags = " --preset preview --resolution-scale 0.08 --holdout-every 4 --seed 2"
                            " --deterministic --no-lidar-loss";
  r = RunCli("train --log " + kKitti + " --out " + two + flags + " --iterations 10");
  ASSERT_EQ(r.code, 0) << r.err;
  r = RunCli("train --log " + kKitti + " --out " + two + flags + " --resume --iterations 16"
             " --position-lr-decay-iterations 3");
  ASSERT_EQ(r.code, 0) << r.err;
  auto slurp = [](const std::string& p) {
    std::ifstream f(p, std::ios::binary);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
  };
  EXPECT_EQ(slurp(one + "/scene.ply"), slurp(two + "/scene.ply"));
  // A config file's schedule may not set the run's end, and a resume may not change a schedule.
  std::ofstream(config, std::ios::trunc) << R"({"schedule": [{"from": 0}, {"from": 5, "set": {"iterations": 9}}]})";
  r = RunCli("train --log " + kKitti + " --out " + one + "/x --config " + config);
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("iterations is the run's end, not a stage's"), std::string::npos) << r.err;
  std::ofstream(config, std::ios::trunc) << R"({"schedule": [{"from": 0}, {"from": 5}]})";
  r = RunCli("train --log " + kKitti + " --out " + one + " --resume --config " + config);
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("a resumed run keeps its schedule"), std::string::npos) << r.err;
}
