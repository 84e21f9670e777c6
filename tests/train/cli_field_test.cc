// streetsim train --field s3gaussian, and what reads its outputs: field.bin beside scene.ply,
// train_meta.json, `streetsim render --scene DIR --time-us T` (clamped to the log's time range),
// `streetsim eval` (PSNR*), and the new flags' bad values.
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "tests/common/cli_runner.h"

namespace {

using streetsim::cli_test::kKitti;
using streetsim::cli_test::kKittiCamera;
using streetsim::cli_test::Result;
using streetsim::cli_test::RunStreetsim;
using streetsim::cli_test::Slurp;

Result RunCli(const std::string& args) {
  const auto dir = std::filesystem::temp_directory_path();
  const std::string out = (dir / ("streetsim_cli_field_out." + std::to_string(getpid()) + ".txt")).string();
  const std::string err = (dir / ("streetsim_cli_field_err." + std::to_string(getpid()) + ".txt")).string();
  Result r = RunStreetsim(args, out, err);
  std::filesystem::remove(out);
  std::filesystem::remove(err);
  return r;
}

TEST(CliField, TrainWritesAFieldThatRenderAndEvalUse) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_field_scene", "run");
  Result r = RunCli("train --log " + kKitti + " --out " + dir +
                    " --iterations 16 --field s3gaussian --static-iterations 8 --field-size small --field-motion-prior 0"
                    " --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3 --checkpoint-every 10");
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* f : {"scene.ply", "field.bin", "train_meta.json", "checkpoint.bin", "checkpoint_field_16.bin"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + f)) << f;
  }
  EXPECT_FALSE(std::filesystem::exists(dir + "/checkpoint_field_10.bin"));  // replaced by the last one
  const nlohmann::json meta = nlohmann::json::parse(Slurp(dir + "/train_meta.json"));
  EXPECT_EQ(meta["field"], "s3gaussian");
  EXPECT_EQ(meta["static_iterations"], 8);
  EXPECT_DOUBLE_EQ(meta["field_lambda_dx"].get<double>(), 1e-3);  // S3Gaussian's Δ sparsity weights
  EXPECT_DOUBLE_EQ(meta["field_lambda_dsh"].get<double>(), 1e-3);
  EXPECT_DOUBLE_EQ(meta["field_l1_time_planes"].get<double>(), 1e-4);  // and its time planes' L1
  EXPECT_DOUBLE_EQ(meta["field_lr_scale"].get<double>(), 10.0);  // streetsim's default learning rates
  EXPECT_EQ(meta["field_lr_decay_iterations"], 30000);
  EXPECT_EQ(meta["field_time_resolution"], 6);  // --field-size small's
  ASSERT_EQ(meta["time_range_us"].size(), 2u);
  const int64_t t0 = meta["time_range_us"][0], t1 = meta["time_range_us"][1];
  EXPECT_LT(t0, t1);

  // Render: no --time-us = the log's first time; times outside the log clamp to its ends.
  const std::string png = dir + "/r.png";
  auto render = [&](const std::string& extra) {
    const Result rr = RunCli("render --scene " + dir + " --camera " + kKittiCamera + " --out-rgb " + png + extra);
    EXPECT_EQ(rr.code, 0) << extra << ": " << rr.err;
    return Slurp(png);
  };
  const std::string at_default = render("");
  EXPECT_FALSE(at_default.empty());
  EXPECT_EQ(render(" --time-us " + std::to_string(t0)), at_default);
  EXPECT_EQ(render(" --time-us " + std::to_string(t0 - 5'000'000)), at_default);
  EXPECT_EQ(render(" --time-us " + std::to_string(t1 + 5'000'000)), render(" --time-us " + std::to_string(t1)));

  // Eval deforms at each held-out frame's time and reports PSNR* (the clip has moving trucks).
  r = RunCli("eval --scene " + dir + " --log " + kKitti + " --no-lidar");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["mean"]["psnr"].is_number());
  EXPECT_TRUE(j["mean"]["psnr_dynamic"].is_number()) << j["mean"].dump();
  EXPECT_TRUE(j["mean"]["psnr_static"].is_number());
  ASSERT_FALSE(j["frames"].empty());
  EXPECT_TRUE(j["frames"][0].contains("psnr_dynamic"));

  // --served: rendered as `streetsim serve` serves it. With the thresholds at 0 nothing is baked
  // and every view is the plain eval's up to float rounding; with huge ones every Gaussian is baked
  // at its time-mean deformation (the counts say so; the 8 fine iterations barely move anything, so
  // PSNR is not compared there: tests/eval/served_scene_test.cc checks the renders on a field that moves).
  const size_t n = j["frames"].size();
  auto served = [&](const std::string& extra) {
    const Result rs = RunCli("eval --scene " + dir + " --log " + kKitti + " --no-lidar --served" + extra);
    EXPECT_EQ(rs.code, 0) << extra << ": " << rs.err;
    EXPECT_NE(rs.err.find("served as by streetsim serve"), std::string::npos) << rs.err;
    return nlohmann::json::parse(rs.out);
  };
  // --field-serving exact: the field's network per view, as the plain eval (the default serving
  // form is compared below).
  const nlohmann::json none = served(" --static-motion-m 0 --static-sh 0 --field-serving exact");
  ASSERT_EQ(none["frames"].size(), n);
  EXPECT_EQ(none["served"]["field_serving"], "exact");
  EXPECT_EQ(none["served"]["static_gaussians"], 0);
  const int64_t total = none["served"]["dynamic_gaussians"];
  EXPECT_GT(total, 0);
  for (size_t i = 0; i < n; ++i) {
    EXPECT_NEAR(none["frames"][i]["psnr"].get<double>(), j["frames"][i]["psnr"].get<double>(), 1e-3) << i;
  }
  const nlohmann::json all = served(" --static-motion-m 1000 --static-sh 1000");
  EXPECT_EQ(all["served"]["dynamic_gaussians"], 0);
  EXPECT_EQ(all["served"]["static_gaussians"], total);
  EXPECT_EQ(all["served"]["motion_threshold_m"], 1000.0);
  const nlohmann::json by_default = served("");
  // The serving form (built here into DIR/field.serving): within 0.05 dB of the exact field per view.
  EXPECT_EQ(by_default["served"]["field_serving"], "served");
  EXPECT_TRUE(std::filesystem::exists(dir + "/field.serving"));
  ASSERT_EQ(by_default["frames"].size(), n);
  for (size_t i = 0; i < n; ++i) {
    EXPECT_NEAR(by_default["frames"][i]["psnr"].get<double>(), j["frames"][i]["psnr"].get<double>(), 0.05) << i;
  }
  EXPECT_EQ(by_default["served"]["motion_threshold_m"], 0.01);
  EXPECT_EQ(by_default["served"]["static_gaussians"].get<int64_t>() + by_default["served"]["dynamic_gaussians"].get<int64_t>(),
            total);
  EXPECT_FALSE(j.contains("served"));  // only with --served

  // A static run into the same directory removes the field (so nothing renders a stale one).
  r = RunCli("train --log " + kKitti + " --out " + dir + " --iterations 2 --resolution-scale 0.12 --holdout-every 0 --voxel 0.5 --field static");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(dir + "/field.bin"));
  EXPECT_EQ(nlohmann::json::parse(Slurp(dir + "/train_meta.json"))["field"], "static");
  // --time-us on a static scene: accepted, nothing to deform.
  render(" --time-us 0");
}

// --field-device vulkan --field-optimizer device: the fine stage steps the field on the device (its
// log says so) and writes the device's field (lavapipe here; skipped without a Vulkan device).
TEST(CliField, FieldOptimizerOnTheDevice) {
  if (RunCli("devices").out.find("vulkan[0]") == std::string::npos) GTEST_SKIP() << "no Vulkan device";
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_field_scene", "device_optimizer");
  const Result r = RunCli("train --log " + kKitti + " --out " + dir +
                          " --iterations 12 --field s3gaussian --static-iterations 8 --field-size small --field-motion-prior 0"
                          " --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3"
                          " --field-device vulkan --field-optimizer device");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("its regularisers and Adam too"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("plane regularisers + field Adam on the device"), std::string::npos) << r.err;
  EXPECT_TRUE(std::filesystem::exists(dir + "/field.bin"));
  EXPECT_TRUE(std::filesystem::exists(dir + "/checkpoint_field_12.bin"));
}

TEST(CliField, ExtendedModulesGrowOnAnS3GaussianRunsResume) {
  // docs/training.md "Growing modules on a trained field": --resume --field extended on an
  // S3Gaussian run's fine-stage checkpoint; checkpoint.json records where they joined, and later
  // resumes count the extension's Adam from there.
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_field_grow", "run");
  const std::string train = "train --log " + kKitti + " --out " + dir + " --static-iterations 8 --checkpoint-every 10";
  const std::string kSmall =
      " --field-size small --field-motion-prior 0 --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3 --no-lidar-loss";
  Result r = RunCli(train + " --iterations 12 --field s3gaussian" + kSmall);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(dir + "/field_ext.bin"));
  r = RunCli(train + " --iterations 15 --resume --field extended --field-modules decoder --field-ext-lr-scale 0.4" +
             " --field-ext-lr-decay-iterations 4500" + kSmall);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* f : {"field_ext.bin", "checkpoint_field_15.bin", "checkpoint_field_15_ext.bin"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + f)) << f;
  }
  const nlohmann::json run = nlohmann::json::parse(Slurp(dir + "/checkpoint.json"));
  EXPECT_EQ(run["field"], "extended");
  EXPECT_EQ(run["field_extension_from"], 4) << run.dump();  // 12 - 8 fine iterations
  const nlohmann::json meta = nlohmann::json::parse(Slurp(dir + "/train_meta.json"));
  EXPECT_EQ(meta["field_modules"], "decoder");
  EXPECT_EQ(meta["field_extension_from"], 4);
  // The modules' own rate is recorded, and apart from the base field's schedule (train_meta.json;
  // the run's settings are config.json's, checkpoint.json holds the checkpoint's state only).
  EXPECT_FALSE(run.contains("field_ext_lr_scale")) << run.dump();
  EXPECT_EQ(meta["field_ext_lr_scale"], 0.4);
  EXPECT_EQ(meta["field_ext_lr_decay_iterations"], 4500);
  EXPECT_EQ(meta["field_lr_scale"], 10.0);
  // The next resume continues the grown extension (its Adam: 3 steps at 15, 5 at 17) and keeps its
  // rate, value by value: a new decay leaves the scale as recorded.
  r = RunCli(train + " --iterations 17 --resume --field extended --field-modules decoder" +
             " --field-ext-lr-decay-iterations 900" + kSmall);
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json resumed = nlohmann::json::parse(Slurp(dir + "/checkpoint.json"));
  EXPECT_EQ(resumed["field_extension_from"], 4);
  const nlohmann::json resumed_meta = nlohmann::json::parse(Slurp(dir + "/train_meta.json"));
  EXPECT_EQ(resumed_meta["field_ext_lr_scale"], 0.4);
  EXPECT_EQ(resumed_meta["field_ext_lr_decay_iterations"], 900);
  r = RunCli("eval --scene " + dir + " --log " + kKitti + " --no-lidar");
  ASSERT_EQ(r.code, 0) << r.err;
  // Other modules than the grown ones are refused; so is a lost extension (never re-grown).
  r = RunCli(train + " --iterations 18 --resume --field extended --field-modules gru" + kSmall);
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("--field-modules decoder"), std::string::npos) << r.err;
  std::filesystem::remove(dir + "/checkpoint_field_17_ext.bin");
  r = RunCli(train + " --iterations 18 --resume --field extended --field-modules decoder" + kSmall);
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("checkpoint_field_17_ext.bin"), std::string::npos) << r.err;
  // A damaged record of where the modules joined is a one-line exit 2 naming the file.
  std::ofstream(dir + "/checkpoint.json", std::ios::trunc)
      << R"({"iteration": 17, "field": "extended", "static_iterations": 8, "field_extension_from": -3})";
  r = RunCli(train + " --iterations 18 --resume --field extended --field-modules decoder" + kSmall);
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("checkpoint.json: field_extension_from"), std::string::npos) << r.err;
  std::filesystem::remove_all(dir);
}

TEST(CliField, BadValuesExitTwoWithOneLine) {
  const std::string train = "train --log " + kKitti + " --out /tmp/streetsim_cli_field_bad";
  const std::string render = "render --camera " + kKittiCamera + " --out-rgb /tmp/streetsim_cli_field_bad.png";
  const std::string eval = "eval --scene /tmp/streetsim_cli_field_bad --log " + kKitti + " --no-lidar";
  for (const std::string& args : {
           train + " --field bogus",
           train + " --iterations 20 --field s3gaussian --static-iterations 20",
           train + " --iterations 20 --field s3gaussian --static-iterations -1",
           train + " --iterations 20 --field s3gaussian --static-iterations x",
           train + " --iterations 20 --field static --static-iterations 5",  // needs --field s3gaussian
           train + " --iterations 100 --field s3gaussian",                   // the default 5000 static iterations
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-size huge",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-device gpu",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-init random",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-optimizer gpu",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lambda-dx -1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lambda-dsh nan",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lambda-dx 1e9",
           train + " --iterations 20 --field static --field-lambda-dx 0.1",  // a static run has no field
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-l1-time-planes -0.1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-l1-time-planes 1e3",
           train + " --iterations 20 --field static --field-l1-time-planes 0.1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-motion-prior -1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-motion-prior nan",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-motion-prior 1e5",
           train + " --iterations 20 --field static --field-motion-prior 1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-motion-prior-scans some",
           train + " --iterations 20 --field static --field-motion-prior-scans all",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-scale 0",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-scale -3",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-scale 1e4",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-scale nan",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-decay-iterations 0",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-lr-decay-iterations 2.5",
           train + " --iterations 20 --field static --field-lr-scale 3",
           train + " --iterations 20 --field static --field-lr-decay-iterations 300",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-time-resolution 1",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-time-resolution 1001",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-time-resolution ten",
           train + " --iterations 20 --field static --field-time-resolution 50",
           train + " --iterations 20 --static-iterations 5 --field extended --field-modules decoder"
                   " --field-decoder-max-dlog-scale -1",
           train + " --iterations 20 --static-iterations 5 --field extended --field-modules decoder"
                   " --field-decoder-max-dlog-scale 51",
           train + " --iterations 20 --static-iterations 5 --field extended --field-modules decoder"
                   " --field-decoder-max-dlog-scale nan",
           train + " --iterations 20 --static-iterations 5 --field extended --field-modules gru"
                   " --field-decoder-max-dlog-scale 2",  // the bound needs the decoder
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-decoder-max-dlog-scale 2",
           train + " --iterations 20 --field s3gaussian --static-iterations 5 --field-ext-lr-scale 0.5",
           train + " --iterations 20 --field static --field-ext-lr-decay-iterations 100",
           train + " --iterations 20 --static-iterations 5 --field extended --field-ext-lr-scale 0",
           train + " --iterations 20 --static-iterations 5 --field extended --field-ext-lr-scale nan",
           train + " --iterations 20 --static-iterations 5 --field extended --field-ext-lr-scale 1e4",
           train + " --iterations 20 --static-iterations 5 --field extended --field-ext-lr-decay-iterations 0",
           train + " --iterations 20 --static-iterations 5 --field extended --field-ext-lr-decay-iterations 1.5",
           eval + " --static-motion-m 0.1",  // needs --served
           eval + " --served --static-sh -1",
           eval + " --served --static-motion-m nan",
           eval + " --served --static-motion-m 1e6",
           eval + " --served --static-sh x",
           eval + " --served --video /tmp/streetsim_cli_field_bad.mp4",
           std::string("serve --static-motion-m -0.5"),
           std::string("serve --static-sh inf"),
           render + " --scene /tmp --ply /tmp/x.ply",
           render + " --ply /tmp/x.ply --time-us 5",
           render + " --scene /tmp --time-us soon",
           render,
       }) {
    const Result r = RunCli(args);
    EXPECT_EQ(r.code, 2) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
  }
}

// Which of an object's scans assign Gaussians to the motion prior (docs/training.md "Motion prior"):
// the run's records, kept by a resume that does not say, a damaged record refused.
TEST(CliField, MotionPriorScansAreRecordedAndKeptByAResume) {
  const std::string common = " --field-size small --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3" +
                             std::string(" --static-iterations 6 --field-motion-prior 0.5");
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_field_scans", "run");
  const auto train = [&](int iterations, const std::string& extra) {
    return RunCli("train --log " + kKitti + " --out " + dir + " --iterations " + std::to_string(iterations) + common +
                  extra);
  };
  const auto recorded = [&](const std::string& file) {
    return nlohmann::json::parse(Slurp(dir + "/" + file))["field_motion_prior_scans"].get<std::string>();
  };
  Result r = train(8, "");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("weight 0.5, last scans;"), std::string::npos) << r.err;  // the default
  EXPECT_EQ(recorded("train_meta.json"), "last");
  r = train(9, " --resume --field-motion-prior-scans all");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("weight 0.5, all scans;"), std::string::npos) << r.err;
  EXPECT_EQ(recorded("train_meta.json"), "all");
  r = train(10, " --resume");  // kept
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("weight 0.5, all scans;"), std::string::npos) << r.err;
  EXPECT_EQ(recorded("train_meta.json"), "all");
  nlohmann::json config = nlohmann::json::parse(Slurp(dir + "/config.json"));
  EXPECT_EQ(config["schedule"][1]["set"]["field-motion-prior-scans"], "all") << config.dump();
  config["settings"]["field-motion-prior-scans"] = "some";
  std::ofstream(dir + "/config.json", std::ios::trunc) << config.dump();
  r = train(11, " --resume");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("config.json: field-motion-prior-scans must be one of last, all, not 'some'"),
            std::string::npos)
      << r.err;
  // A run from before config.json whose checkpoint.json recorded no scans: its last ones.
  std::filesystem::remove(dir + "/config.json");
  nlohmann::json j = nlohmann::json::parse(Slurp(dir + "/checkpoint.json"));
  j["static_iterations"] = 6;  // what such a run recorded
  j["field_motion_prior"] = 0.5;
  std::ofstream(dir + "/checkpoint.json", std::ios::trunc) << j.dump();
  r = train(11, " --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("weight 0.5, last scans;"), std::string::npos) << r.err;
  EXPECT_EQ(recorded("train_meta.json"), "last");
}

// --field's default: S3Gaussian's field when the run has a fine stage, static otherwise; a resumed
// run keeps the field its directory shows (docs/training.md "Default field").
TEST(CliField, DefaultFieldFollowsTheRunAndItsDirectory) {
  const std::string common = " --field-size small --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3";
  const std::string short_dir = streetsim::testing::ScratchDir("streetsim_cli_field_default", "short");
  Result r = RunCli("train --log " + kKitti + " --out " + short_dir + " --iterations 6" + common);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(short_dir + "/field.bin"));  // 6 <= the 5000-iteration warm-up
  EXPECT_EQ(nlohmann::json::parse(Slurp(short_dir + "/train_meta.json"))["field"], "static");
  EXPECT_EQ(nlohmann::json::parse(Slurp(short_dir + "/checkpoint.json"))["field"], "static");

  const std::string staged_dir = streetsim::testing::ScratchDir("streetsim_cli_field_default", "staged");
  r = RunCli("train --log " + kKitti + " --out " + staged_dir + " --iterations 10 --static-iterations 6" +
             " --field-lambda-dx 0.25 --field-lambda-dsh 0 --field-l1-time-planes 0.5" +
             " --field-lr-scale 2.5 --field-lr-decay-iterations 4000 --field-time-resolution 5" +
             " --field-motion-prior 0.5" + common);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("preset quality (10 iterations, S3Gaussian's field after 6 static)"), std::string::npos)
      << r.err;
  // The motion prior tracks the training frames' scans only (78 frames, every 10th held out).
  EXPECT_NE(r.err.find("moving objects from 71 training frames' LiDAR"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("Gaussians on moving objects"), std::string::npos) << r.err;
  // Where the fine stage's time went, once at the end (docs/training.md "Fine-stage timings").
  EXPECT_NE(r.err.find("fine stage: 4 iterations, ms per iteration: field forward"), std::string::npos) << r.err;
  // The progress's ETA says when it covers the static stage only (the fine stage is slower).
  const size_t first_line = r.err.find("] 1/10 "), last_line = r.err.find("] 10/10 ");
  ASSERT_NE(first_line, std::string::npos) << r.err;
  ASSERT_NE(last_line, std::string::npos) << r.err;
  EXPECT_NE(r.err.substr(first_line, r.err.find('\n', first_line) - first_line).find("(static stage"),
            std::string::npos) << r.err;
  EXPECT_EQ(r.err.substr(last_line, r.err.find('\n', last_line) - last_line).find("(static stage"),
            std::string::npos) << r.err;
  EXPECT_TRUE(std::filesystem::exists(staged_dir + "/field.bin"));
  const nlohmann::json staged_meta = nlohmann::json::parse(Slurp(staged_dir + "/train_meta.json"));
  EXPECT_EQ(staged_meta["field"], "s3gaussian");
  EXPECT_DOUBLE_EQ(staged_meta["field_lambda_dx"].get<double>(), 0.25);  // the weights given
  EXPECT_DOUBLE_EQ(staged_meta["field_lambda_dsh"].get<double>(), 0.0);
  EXPECT_DOUBLE_EQ(staged_meta["field_l1_time_planes"].get<double>(), 0.5);
  EXPECT_DOUBLE_EQ(staged_meta["field_motion_prior"].get<double>(), 0.5);
  EXPECT_DOUBLE_EQ(staged_meta["field_lr_scale"].get<double>(), 2.5);  // the learning-rate schedule given
  EXPECT_EQ(staged_meta["field_lr_decay_iterations"], 4000);
  EXPECT_EQ(staged_meta["field_time_resolution"], 5);  // the field's cells along time (spec 25)
  const nlohmann::json staged_run = nlohmann::json::parse(Slurp(staged_dir + "/checkpoint.json"));
  EXPECT_EQ(staged_run["field"], "s3gaussian");
  EXPECT_EQ(staged_run["iteration"], 10);
  EXPECT_FALSE(staged_run.contains("field_lr_scale")) << staged_run.dump();  // config.json's

  // A resume keeps the run's own config (config.json): its learning-rate schedule and motion
  // prior; a value given wins from the checkpoint on, the others stay the run's.
  auto resume_to = [&](int iterations, const std::string& extra = "") {
    return RunCli("train --log " + kKitti + " --out " + staged_dir + " --resume --iterations " +
                  std::to_string(iterations) + common + extra);
  };
  auto meta_lr = [&]() {
    const nlohmann::json m = nlohmann::json::parse(Slurp(staged_dir + "/train_meta.json"));
    return std::make_pair(m["field_lr_scale"].get<double>(), m["field_lr_decay_iterations"].get<int>());
  };
  auto meta_prior = [&]() {
    return nlohmann::json::parse(Slurp(staged_dir + "/train_meta.json"))["field_motion_prior"].get<double>();
  };
  r = resume_to(11);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(meta_lr(), std::make_pair(2.5, 4000));
  EXPECT_DOUBLE_EQ(meta_prior(), 0.5);  // and its motion prior (a segment must not drop it)
  EXPECT_NE(r.err.find("Gaussians on moving objects"), std::string::npos) << r.err;
  r = resume_to(12, " --field-lr-scale 4");  // an explicit value wins, the other stays the run's
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("from iteration 11: field-lr-scale"), std::string::npos) << r.err;
  EXPECT_EQ(meta_lr(), std::make_pair(4.0, 4000));
  r = resume_to(13, " --field-lr-decay-iterations 700");  // annealing keeps the run's scale
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(meta_lr(), std::make_pair(4.0, 700));
  r = resume_to(14, " --field-motion-prior 0");  // turns it off
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(meta_lr(), std::make_pair(4.0, 700));
  EXPECT_DOUBLE_EQ(meta_prior(), 0.0);
  EXPECT_EQ(r.err.find("Gaussians on moving objects"), std::string::npos) << r.err;
  // config.json holds the run's history: each change is a stage from the iteration it began at.
  const nlohmann::json config = nlohmann::json::parse(Slurp(staged_dir + "/config.json"));
  ASSERT_GE(config["schedule"].size(), 4u) << config.dump();
  EXPECT_EQ(config["schedule"][1]["from"], 11);
  EXPECT_EQ(config["schedule"][1]["set"]["field-lr-scale"], 4.0);
  EXPECT_EQ(config["settings"]["field-lr-scale"], 2.5);

  // A directory from before config.json: its checkpoint.json decides (a static run stays static
  // past the warm-up), and a damaged one is refused naming it. The checkpoint here is a header
  // only (magic + iteration), so the run then fails loading it.
  const std::string dir = streetsim::testing::ScratchDir("streetsim_cli_field_default", "resume");
  {
    std::ofstream f(dir + "/checkpoint.bin", std::ios::binary | std::ios::trunc);
    const int64_t iteration = 6000;
    f.write("SSTRN001", 8);
    f.write(reinterpret_cast<const char*>(&iteration), sizeof(iteration));
  }
  const std::string resume = "train --log " + kKitti + " --out " + dir + " --iterations 30000 --resume" + common;
  auto record = [&](const std::string& text) { std::ofstream(dir + "/checkpoint.json", std::ios::trunc) << text; };
  record(R"({"iteration": 6000, "field": "static"})");
  r = RunCli(resume);
  EXPECT_NE(r.err.find("predates config.json"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("30000 iterations, static model"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("corrupt checkpoint"), std::string::npos) << r.err;
  for (const char* damaged : {"{\"field\": ", R"({"field": "dynamic"})"}) {
    std::filesystem::remove(dir + "/config.json");
    record(damaged);
    r = RunCli(resume);
    EXPECT_EQ(r.code, 2) << damaged << ": " << r.err;
    EXPECT_NE(r.err.find("checkpoint.json"), std::string::npos) << damaged << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << damaged << ": " << r.err;
  }
}

}  // namespace
