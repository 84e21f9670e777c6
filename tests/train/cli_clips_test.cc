// `streetsim train --clip-frames N` end to end on a 19-frame copy of the KITTI clip (links to the
// shared data): two clips and DIR/clips.json; `render --scene DIR --time-us T` renders the clip of
// T; `eval --scene DIR` evaluates every held-out frame once, each by its clip; --resume of a
// finished set trains nothing; bad --clip-frames values and mismatched resumes exit 2.
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"

namespace {

namespace fs = std::filesystem;

const fs::path kDay = fs::path(STREETSIM_DATA_DIR) / "kitti_raw/2011_09_26";
const char* kDrive = "2011_09_26_drive_sfnd_sync";

using streetsim::cli_test::kKittiCamera;
using streetsim::cli_test::Result;
using streetsim::cli_test::RunStreetsim;
using streetsim::cli_test::Slurp;

fs::path Scratch() {
  return fs::path(::testing::TempDir()) / ("streetsim_cli_clips_" + std::to_string(getpid()));
}

Result RunCli(const std::string& args) {
  const std::string out = (Scratch() / "stdout.txt").string(), err = (Scratch() / "stderr.txt").string();
  return RunStreetsim(args, out, err);
}

// The first `frames` frames of the shared drive, as links, beside links to the day's calibration.
std::string ShortLog(int frames) {
  const fs::path day = Scratch() / "log/2011_09_26";
  const fs::path drive = day / kDrive;
  fs::create_directories(drive / "image_02/data");
  fs::create_directories(drive / "velodyne_points/data");
  for (const char* calib : {"calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"}) {
    fs::create_symlink(kDay / calib, day / calib);
  }
  std::ifstream poses(kDay / kDrive / "poses_velo_icp_estimated.txt");
  std::ofstream short_poses(drive / "poses_velo_icp_estimated.txt");
  std::string line;
  for (int i = 0; i < frames && std::getline(poses, line);) {
    short_poses << line << "\n";
    i += !line.empty() && line[0] != '#';  // comments are not poses
  }
  for (int i = 0; i < frames; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "%010d", i);
    fs::create_symlink(kDay / kDrive / "image_02/data" / (std::string(name) + ".png"),
                       drive / "image_02/data" / (std::string(name) + ".png"));
    fs::create_symlink(kDay / kDrive / "velodyne_points/data" / (std::string(name) + ".bin"),
                       drive / "velodyne_points/data" / (std::string(name) + ".bin"));
  }
  return drive.string();
}

class CliClips : public ::testing::Test {
 protected:
  void SetUp() override {
    fs::remove_all(Scratch());
    fs::create_directories(Scratch());
  }
  void TearDown() override { fs::remove_all(Scratch()); }
};

TEST_F(CliClips, TrainRenderEvalResume) {
  const std::string log = ShortLog(19);
  const std::string dir = (Scratch() / "set").string();
  const std::string train_args = "train --log " + log + " --out " + dir +
                                 " --iterations 6 --field s3gaussian --static-iterations 3 --field-size small --field-motion-prior 0"
                                 " --resolution-scale 0.12 --voxel 0.5 --seed 3 --no-lidar-loss --clip-frames 8";
  Result r = RunCli(train_args);
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json clips = nlohmann::json::parse(Slurp(dir + "/clips.json"));
  EXPECT_EQ(clips["clip_frames"], 8);
  EXPECT_EQ(clips["num_frames"], 19);
  ASSERT_EQ(clips["clips"].size(), 2u);
  EXPECT_EQ(clips["clips"][0]["frames"], nlohmann::json({0, 8}));
  EXPECT_EQ(clips["clips"][1]["frames"], nlohmann::json({8, 19}));  // the 3-frame tail joined clip 1
  EXPECT_EQ(clips["clips"][1]["dir"], "clip_001");
  EXPECT_EQ(clips["overlap_frames"], 0);  // the default, a tenth of 8 frames
  EXPECT_EQ(clips["clips"][1]["trained_frames"], nlohmann::json({8, 19}));
  const int64_t end0 = clips["clips"][0]["time_range_us"][1], start1 = clips["clips"][1]["time_range_us"][0];
  const int64_t end1 = clips["clips"][1]["time_range_us"][1];
  ASSERT_LT(end0, start1);
  for (const char* c : {"clip_000", "clip_001"}) {
    for (const char* f : {"scene.ply", "field.bin", "train_meta.json", "checkpoint.bin", "scene.json"}) {
      EXPECT_TRUE(fs::exists(fs::path(dir) / c / f)) << c << "/" << f;
    }
  }
  const nlohmann::json meta1 = nlohmann::json::parse(Slurp(dir + "/clip_001/train_meta.json"));
  EXPECT_EQ(meta1["time_range_us"], nlohmann::json({start1, end1}));  // the clip's own time axis

  // Render: the clip set at T is the clip of T rendered on its own (a time between the clips goes
  // to the nearer one, times outside the log to the first / last clip). A quarter-size camera.
  nlohmann::json cam = nlohmann::json::parse(Slurp(kKittiCamera));
  for (const char* k : {"width", "height"}) cam[k] = cam[k].get<int>() / 4;
  for (const char* k : {"fx", "fy", "cx", "cy"}) cam[k] = cam[k].get<double>() / 4;
  const std::string camera = (Scratch() / "camera.json").string();
  std::ofstream(camera) << cam.dump();
  auto render = [&](const std::string& scene, const std::string& time) {
    const std::string png = (Scratch() / "r.png").string();
    const Result rr = RunCli("render --scene " + scene + " --camera " + camera + " --out-rgb " + png +
                             (time.empty() ? "" : " --time-us " + time));
    EXPECT_EQ(rr.code, 0) << rr.err;
    return Slurp(png);
  };
  const std::string clip0 = dir + "/clip_000", clip1 = dir + "/clip_001";
  const std::string t1 = std::to_string((start1 + end1) / 2);
  EXPECT_EQ(render(dir, t1), render(clip1, t1));
  EXPECT_NE(render(dir, t1), render(clip0, t1));
  EXPECT_EQ(render(dir, ""), render(clip0, ""));
  EXPECT_EQ(render(dir, std::to_string(end0 + (start1 - end0) / 4)), render(clip0, std::to_string(end0)));
  EXPECT_EQ(render(dir, std::to_string(end1 + 10'000'000)), render(clip1, std::to_string(end1)));

  // Eval: held-out frames 3, 7, 11, 15, each once, by its clip.
  r = RunCli("eval --scene " + dir + " --log " + log + " --no-lidar");
  ASSERT_EQ(r.code, 0) << r.err;
  nlohmann::json j = nlohmann::json::parse(r.out);
  ASSERT_EQ(j["frames"].size(), 4u);
  std::vector<int> frames, clip_of;
  for (const auto& f : j["frames"]) frames.push_back(f["frame"]), clip_of.push_back(f["clip"]);
  EXPECT_EQ(frames, (std::vector<int>{3, 7, 11, 15}));
  EXPECT_EQ(clip_of, (std::vector<int>{0, 0, 1, 1}));
  // The seam where clip 0 hands over to clip 1: frames 7 and 8 rendered by both.
  ASSERT_EQ(j["seams"].size(), 1u);
  EXPECT_EQ(j["seams"][0]["frames"], nlohmann::json({7, 8}));
  EXPECT_EQ(j["seams"][0]["views"], 2);
  const double between = j["seams"][0]["psnr_between_clips"];
  EXPECT_GT(between, 5);
  EXPECT_LT(between, 100);  // two different reconstructions
  EXPECT_GT(j["seams"][0]["switch_time_us"].get<int64_t>(), end0);
  EXPECT_LE(j["seams"][0]["switch_time_us"].get<int64_t>(), start1);
  EXPECT_NE(r.err.find("seam clip 0 | 1"), std::string::npos) << r.err;
  const double seam_before = j["seams"][0]["psnr_before"], seam_after = j["seams"][0]["psnr_after"];
  // Frame 11 scores as clip 1 scores it on its own.
  Result own = RunCli("eval --scene " + clip1 + " --log " + log + " --no-lidar");
  ASSERT_EQ(own.code, 0) << own.err;
  const nlohmann::json jo = nlohmann::json::parse(own.out);
  for (const auto& f : jo["frames"]) {
    if (f["frame"] == 11) {
      EXPECT_DOUBLE_EQ(f["psnr"].get<double>(), j["frames"][2]["psnr"].get<double>());
    }
  }
  // The seam's scores are each clip's own, with its own sky: clip k evaluated alone on frame 7
  // (held out) and frame 8 (trained), averaged (one camera each).
  auto frame_psnr = [&](const std::string& scene, const std::string& split, int frame) {
    Result e = RunCli("eval --scene " + scene + " --log " + log + " --no-lidar --split " + split);
    EXPECT_EQ(e.code, 0) << e.err;
    const nlohmann::json je = nlohmann::json::parse(e.out);
    for (const auto& f : je["frames"]) {
      if (f["frame"] == frame) return f["psnr"].get<double>();
    }
    ADD_FAILURE() << "frame " << frame << " not in " << scene << "'s " << split << " split";
    return 0.0;
  };
  EXPECT_NEAR(seam_before, (frame_psnr(clip0, "test", 7) + frame_psnr(clip0, "train", 8)) / 2, 1e-9);
  EXPECT_NEAR(seam_after, (frame_psnr(clip1, "test", 7) + frame_psnr(clip1, "train", 8)) / 2, 1e-9);
  // A clip with no view of the split is still read for its seams: every 10th frame held out
  // leaves clip 0 (frames 0-7) none, and the seam scores do not depend on the split.
  Result sparse = RunCli("eval --scene " + dir + " --log " + log + " --no-lidar --holdout-every 10");
  ASSERT_EQ(sparse.code, 0) << sparse.err;
  const nlohmann::json js = nlohmann::json::parse(sparse.out);
  ASSERT_EQ(js["frames"].size(), 1u);
  EXPECT_EQ(js["frames"][0]["frame"], 9);
  EXPECT_EQ(js["frames"][0]["clip"], 1);
  ASSERT_EQ(js["seams"].size(), 1u);
  EXPECT_DOUBLE_EQ(js["seams"][0]["psnr_before"].get<double>(), seam_before);
  EXPECT_DOUBLE_EQ(js["seams"][0]["psnr_after"].get<double>(), seam_after);
  // Training split: every training frame once.
  r = RunCli("eval --scene " + dir + " --log " + log + " --no-lidar --split train");
  ASSERT_EQ(r.code, 0) << r.err;
  j = nlohmann::json::parse(r.out);
  std::set<int> seen;
  for (const auto& f : j["frames"]) EXPECT_TRUE(seen.insert(f["frame"].get<int>()).second);
  EXPECT_EQ(seen.size(), 15u);

  // Resume of a finished set: nothing retrained.
  const auto t_ply = fs::last_write_time(fs::path(clip1) / "scene.ply");
  r = RunCli(train_args + " --resume");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(fs::last_write_time(fs::path(clip1) / "scene.ply"), t_ply);
  EXPECT_EQ(r.err.find("clip 0, frames"), std::string::npos) << r.err;
  // A resume with another plan: exit 2, nothing touched; without --clip-frames it keeps the
  // set's own (config.json), nothing retrained.
  r = RunCli("train --log " + log + " --out " + dir + " --iterations 6 --clip-frames 6 --resume");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("clips of 8 frames"), std::string::npos) << r.err;
  r = RunCli("train --log " + log + " --out " + dir + " --iterations 6 --resume");
  EXPECT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(fs::last_write_time(fs::path(clip1) / "scene.ply"), t_ply);

  // A hostile manifest: consumers refuse it.
  std::ofstream(dir + "/clips.json", std::ios::trunc)
      << R"({"version": 1, "clip_frames": 8, "num_frames": 19, "clips": [{"index": 0, "dir": "../../etc",)"
      << R"( "frames": [0, 19], "time_range_us": [0, 1800000], "done": true}]})";
  r = RunCli("render --scene " + dir + " --camera " + kKittiCamera + " --out-rgb " + (Scratch() / "x.png").string());
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("clips.json"), std::string::npos) << r.err;
  r = RunCli("eval --scene " + dir + " --log " + log + " --no-lidar");
  EXPECT_EQ(r.code, 2);
}

// Without --clip-overlap a clip trains on a tenth of a clip of each neighbour's frames: clip 1 of
// 10-frame clips on frames 9..18, its field's time axis from frame 9 (clip 0's last frame).
TEST_F(CliClips, DefaultOverlapIsATenthOfAClip) {
  const std::string log = ShortLog(19);
  const std::string dir = (Scratch() / "set").string();
  const Result r = RunCli("train --log " + log + " --out " + dir +
                          " --iterations 4 --field s3gaussian --static-iterations 2 --field-size small --field-motion-prior 0"
                          " --resolution-scale 0.12 --voxel 0.5 --seed 3 --no-lidar-loss --clip-frames 10");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json clips = nlohmann::json::parse(Slurp(dir + "/clips.json"));
  EXPECT_EQ(clips["overlap_frames"], 1);
  ASSERT_EQ(clips["clips"].size(), 2u);
  EXPECT_EQ(clips["clips"][0]["frames"], nlohmann::json({0, 10}));
  EXPECT_EQ(clips["clips"][0]["trained_frames"], nlohmann::json({0, 11}));
  EXPECT_EQ(clips["clips"][1]["trained_frames"], nlohmann::json({9, 19}));
  const nlohmann::json meta1 = nlohmann::json::parse(Slurp(dir + "/clip_001/train_meta.json"));
  EXPECT_EQ(meta1["time_range_us"][0], clips["clips"][0]["time_range_us"][1]);
  EXPECT_NE(r.err.find("clip 1, frames [10, 19) trained on [9, 19)"), std::string::npos) << r.err;
  // A resume keeps the set's overlap: a set written before overlaps existed (no overlap keys)
  // resumes as one without (nothing left to train); another overlap given explicitly is refused.
  nlohmann::json old = clips;
  old.erase("overlap_frames");
  for (auto& c : old["clips"]) c.erase("trained_frames");
  std::ofstream(dir + "/clips.json", std::ios::trunc) << old.dump();
  const std::string resume = "train --log " + log + " --out " + dir +
                             " --iterations 4 --field s3gaussian --static-iterations 2 --field-size small --field-motion-prior 0"
                             " --resolution-scale 0.12 --voxel 0.5 --seed 3 --no-lidar-loss --clip-frames 10 --resume";
  Result rr = RunCli(resume);
  EXPECT_EQ(rr.code, 0) << rr.err;
  EXPECT_EQ(rr.err.find("trained on"), std::string::npos) << rr.err;  // no clip retrained
  rr = RunCli(resume + " --clip-overlap 1");
  EXPECT_EQ(rr.code, 2);
  EXPECT_NE(rr.err.find("overlap 0"), std::string::npos) << rr.err;
}

// Low resolution first applies to each clip: its first iterations (here into its fine stage,
// which starts from the previous clip's field) at the low scale, the rest at the run's.
TEST_F(CliClips, EachClipTrainsLowResolutionFirst) {
  const std::string log = ShortLog(12);
  const std::string dir = (Scratch() / "set").string();
  const Result r = RunCli("train --log " + log + " --out " + dir +
                          " --iterations 5 --field s3gaussian --static-iterations 2 --field-size small --field-motion-prior 0"
                          " --resolution-scale 0.12 --low-res-scale 0.06 --low-res-iterations 3"
                          " --voxel 0.5 --seed 3 --no-lidar-loss --clip-frames 6");
  ASSERT_EQ(r.code, 0) << r.err;
  size_t stages = 0;
  for (size_t at = 0; (at = r.err.find("low-resolution stage: iterations 1-3 at resolution scale 0.06", at)) !=
                      std::string::npos;
       ++at) {
    ++stages;
  }
  EXPECT_EQ(stages, 2u) << r.err;
  for (const char* c : {"clip_000", "clip_001"}) {
    const nlohmann::json meta = nlohmann::json::parse(Slurp(dir + "/" + c + "/train_meta.json"));
    EXPECT_EQ(meta["iterations"], 5) << c;
    EXPECT_DOUBLE_EQ(meta["resolution_scale"].get<double>(), 0.12) << c;
    EXPECT_EQ(meta["low_res_iterations"], 3) << c;
    EXPECT_TRUE(fs::exists(fs::path(dir) / c / "field.bin")) << c;
  }
}

TEST_F(CliClips, BadClipFramesExit2) {
  const std::string log = ShortLog(4);
  for (const char* v : {"-3", "1", "3", "x", "2.5"}) {
    const Result r = RunCli("train --log " + log + " --out " + (Scratch() / "bad").string() +
                            " --iterations 2 --clip-frames " + v);
    EXPECT_EQ(r.code, 2) << v;
    EXPECT_NE(r.err.find("--clip-frames"), std::string::npos) << v << ": " << r.err;
  }
  EXPECT_FALSE(fs::exists(Scratch() / "bad"));
  // --clip-overlap: an integer in 0 .. N / 2, and only with --clip-frames.
  for (const char* v : {"-1", "5", "x", "1.5"}) {
    const Result r = RunCli("train --log " + log + " --out " + (Scratch() / "bad").string() +
                            " --iterations 2 --clip-frames 8 --clip-overlap " + v);
    EXPECT_EQ(r.code, 2) << v;
    EXPECT_NE(r.err.find("clip-overlap"), std::string::npos) << v << ": " << r.err;
  }
  const Result r = RunCli("train --log " + log + " --out " + (Scratch() / "bad").string() +
                          " --iterations 2 --clip-overlap 2");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("clip-overlap needs clip-frames"), std::string::npos) << r.err;
  EXPECT_FALSE(fs::exists(Scratch() / "bad"));
}

}  // namespace
