// Clip sets (scene/train/clips.h, clip_training.h; docs/training.md "Clips"): the plan and its
// remainder rule, the manifest and what a damaged or hostile one gets, picking a clip for a time,
// merged metrics, and training on a short KITTI log: clip 1's field starts from clip 0's, a run
// killed in clip 1 resumes there without retraining clip 0 and ends where an uninterrupted run does.
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/field_io.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "render/engine.h"
#include "scene/train/clip_seams.h"
#include "scene/train/clip_training.h"
#include "scene/train/clips.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;

const char* kKitti = STREETSIM_DATA_DIR "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

std::string TempDir(const std::string& name) { return testing::ScratchDir("streetsim_clips_test", name); }

std::vector<ClipRange> Plan(int frames, int clip_frames) {
  absl::StatusOr<std::vector<ClipRange>> p = PlanClips(frames, clip_frames);
  EXPECT_TRUE(p.ok()) << p.status();
  return p.ok() ? *p : std::vector<ClipRange>{};
}

TEST(ClipPlan, FullClipsAndTheRemainderRule) {
  EXPECT_EQ(Plan(19, 8), (std::vector<ClipRange>{{0, 8}, {8, 19}}));           // tail of 3 < 4 joins
  EXPECT_EQ(Plan(20, 8), (std::vector<ClipRange>{{0, 8}, {8, 16}, {16, 20}}));  // tail of 4 = N/2 stays
  EXPECT_EQ(Plan(100, 50), (std::vector<ClipRange>{{0, 50}, {50, 100}}));
  EXPECT_EQ(Plan(124, 50), (std::vector<ClipRange>{{0, 50}, {50, 124}}));       // 24 < 25
  EXPECT_EQ(Plan(125, 50), (std::vector<ClipRange>{{0, 50}, {50, 100}, {100, 125}}));
  EXPECT_EQ(Plan(74, 50), (std::vector<ClipRange>{{0, 74}}));  // up to 1.5 N: one clip
  EXPECT_EQ(Plan(30, 50), (std::vector<ClipRange>{{0, 30}}));
  EXPECT_EQ(Plan(78, 0), (std::vector<ClipRange>{{0, 78}}));   // 0: the whole log
  EXPECT_EQ(Plan(9, 5), (std::vector<ClipRange>{{0, 5}, {5, 9}}));  // odd N: tail >= ceil(5 / 2)
  EXPECT_EQ(Plan(7, 5), (std::vector<ClipRange>{{0, 7}}));
}

TEST(ClipPlan, OverlapWidensTheTrainedFramesInsideTheLog) {
  EXPECT_EQ(TrainedFrames({0, 8}, 2, 20), (ClipRange{0, 10}));  // nothing before the log
  EXPECT_EQ(TrainedFrames({8, 16}, 2, 20), (ClipRange{6, 18}));
  EXPECT_EQ(TrainedFrames({16, 20}, 2, 20), (ClipRange{14, 20}));  // nothing after it
  EXPECT_EQ(TrainedFrames({8, 16}, 0, 20), (ClipRange{8, 16}));
}

TEST(ClipPlan, AbsurdValuesAreClearErrors) {
  for (int n : {-3, -1, 1, 2, 3}) {
    absl::StatusOr<std::vector<ClipRange>> p = PlanClips(78, n);
    ASSERT_FALSE(p.ok()) << n;
    EXPECT_EQ(p.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(p.status().message().find("--clip-frames"), std::string::npos) << p.status();
  }
  EXPECT_FALSE(PlanClips(0, 8).ok());
  for (int overlap : {-1, 5, 100}) {
    const absl::Status s = CheckClipOverlap(8, overlap);
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << overlap;
    EXPECT_NE(s.message().find("--clip-overlap"), std::string::npos) << s;
  }
  EXPECT_TRUE(CheckClipOverlap(8, 4).ok());
  EXPECT_TRUE(CheckClipOverlap(8, 0).ok());
  EXPECT_TRUE(PlanClips(78, kMinClipFrames).ok());
}

ClipSet ThreeClips() {
  ClipSet s;
  s.clip_frames = 8;
  s.num_frames = 20;
  const int64_t dt = 100'000;
  for (auto [a, b] : std::vector<std::pair<int, int>>{{0, 8}, {8, 16}, {16, 20}}) {
    ClipEntry e;
    e.frames = {a, b};
    e.start_us = a * dt;
    e.end_us = (b - 1) * dt;
    e.dir = ClipDirName(static_cast<int>(s.clips.size()));
    e.done = a == 0;
    s.clips.push_back(e);
  }
  return s;
}

TEST(ClipManifest, RoundTrip) {
  const std::string dir = TempDir("roundtrip");
  absl::StatusOr<std::optional<ClipSet>> none = ReadClipSet(dir);
  ASSERT_TRUE(none.ok());
  EXPECT_FALSE(none->has_value());
  const ClipSet s = ThreeClips();
  ASSERT_TRUE(WriteClipSet(s, dir).ok());
  absl::StatusOr<std::optional<ClipSet>> back = ReadClipSet(dir);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_TRUE(back->has_value());
  const ClipSet& b = **back;
  EXPECT_EQ(b.clip_frames, 8);
  EXPECT_EQ(b.num_frames, 20);
  ASSERT_EQ(b.clips.size(), 3u);
  for (size_t k = 0; k < 3; ++k) {
    EXPECT_EQ(b.clips[k].frames, s.clips[k].frames);
    EXPECT_EQ(b.clips[k].start_us, s.clips[k].start_us);
    EXPECT_EQ(b.clips[k].end_us, s.clips[k].end_us);
    EXPECT_EQ(b.clips[k].dir, s.clips[k].dir);
    EXPECT_EQ(b.clips[k].done, s.clips[k].done);
  }
  EXPECT_FALSE(fs::exists(fs::path(dir) / "clips.json.tmp"));
}

TEST(ClipManifest, OverlapRoundTripsAndOldManifestsHaveNone) {
  const std::string dir = TempDir("overlap");
  ClipSet s = ThreeClips();
  s.overlap_frames = 2;
  ASSERT_TRUE(WriteClipSet(s, dir).ok());
  absl::StatusOr<std::optional<ClipSet>> back = ReadClipSet(dir);
  ASSERT_TRUE(back.ok() && back->has_value()) << back.status();
  EXPECT_EQ((*back)->overlap_frames, 2);
  EXPECT_EQ((*back)->trained(1), (ClipRange{6, 18}));
  EXPECT_EQ((*back)->clips[1].frames, (ClipRange{8, 16}));
  // A manifest written before overlaps: no "overlap_frames", no "trained_frames".
  const std::string path = (fs::path(dir) / kClipManifestName).string();
  nlohmann::json j = nlohmann::json::parse(std::ifstream(path));
  j.erase("overlap_frames");
  for (auto& c : j["clips"]) c.erase("trained_frames");
  std::ofstream(path, std::ios::trunc) << j.dump();
  back = ReadClipSet(dir);
  ASSERT_TRUE(back.ok() && back->has_value()) << back.status();
  EXPECT_EQ((*back)->overlap_frames, 0);
  EXPECT_EQ((*back)->trained(1), (ClipRange{8, 16}));
}

// Writes `s`'s JSON after `edit`, then reads it back.
absl::Status ReadEdited(const std::string& dir, const std::function<void(nlohmann::json&)>& edit) {
  if (absl::Status st = WriteClipSet(ThreeClips(), dir); !st.ok()) return st;
  const std::string path = (fs::path(dir) / kClipManifestName).string();
  std::ifstream in(path);
  nlohmann::json j = nlohmann::json::parse(in);
  in.close();
  edit(j);
  std::ofstream(path, std::ios::trunc) << j.dump();
  return ReadClipSet(dir).status();
}

TEST(ClipManifest, DamagedOrHostileManifestsAreRefused) {
  const std::string dir = TempDir("hostile");
  using J = nlohmann::json;
  const std::vector<std::pair<std::string, std::function<void(J&)>>> cases = {
      {"escaping dir", [](J& j) { j["clips"][1]["dir"] = "../../etc"; }},
      {"absolute dir", [](J& j) { j["clips"][0]["dir"] = "/etc"; }},
      {"nested dir", [](J& j) { j["clips"][0]["dir"] = "clip_000/../../x"; }},
      {"another clip's dir", [](J& j) { j["clips"][0]["dir"] = "clip_001"; }},
      {"dir not a string", [](J& j) { j["clips"][0]["dir"] = 3; }},
      {"missing key", [](J& j) { j["clips"][2].erase("time_range_us"); }},
      {"gap between clips", [](J& j) { j["clips"][1]["frames"] = {9, 16}; }},
      {"overlap", [](J& j) { j["clips"][1]["frames"] = {7, 16}; }},
      {"empty clip", [](J& j) { j["clips"][1]["frames"] = {8, 8}; }},
      {"not covering the log", [](J& j) { j["num_frames"] = 30; }},
      {"past the log", [](J& j) { j["clips"][2]["frames"] = {16, 40}; }},
      {"time backwards", [](J& j) { j["clips"][1]["time_range_us"] = {900000, 800000}; }},
      {"times out of order", [](J& j) { j["clips"][2]["time_range_us"] = {0, 1900000}; }},
      {"wrong index", [](J& j) { j["clips"][1]["index"] = 5; }},
      {"no clips", [](J& j) { j["clips"] = J::array(); }},
      {"clips not an array", [](J& j) { j["clips"] = "clip_000"; }},
      {"unknown version", [](J& j) { j["version"] = 2; }},
      {"negative clip_frames", [](J& j) { j["clip_frames"] = -3; }},
      {"huge num_frames", [](J& j) { j["num_frames"] = 2'000'000'000; }},
      {"frames not 2 numbers", [](J& j) { j["clips"][0]["frames"] = {0}; }},
      {"trained frames not the overlap's", [](J& j) { j["clips"][1]["trained_frames"] = {0, 20}; }},
      {"trained frames not 2 numbers", [](J& j) { j["clips"][1]["trained_frames"] = {8}; }},
      {"overlap above half a clip", [](J& j) { j["overlap_frames"] = 5; }},
      {"negative overlap", [](J& j) { j["overlap_frames"] = -1; }},
      {"overlap not a number", [](J& j) { j["overlap_frames"] = "2"; }},
  };
  for (const auto& [what, edit] : cases) {
    const absl::Status s = ReadEdited(dir, edit);
    EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss) << what << ": " << s;
    EXPECT_NE(s.message().find("clips.json"), std::string::npos) << what << ": " << s;
  }
  // Not JSON at all, and truncated.
  for (const std::string text : {"not json", "{\"version\": 1, \"clips\": [", ""}) {
    std::ofstream(fs::path(dir) / kClipManifestName, std::ios::trunc) << text;
    EXPECT_EQ(ReadClipSet(dir).status().code(), absl::StatusCode::kDataLoss) << text;
  }
}

TEST(ClipManifest, ClipDirectoryLinkedOutOfTheSetIsRefused) {
  const std::string dir = TempDir("link");
  const std::string outside = TempDir("link_outside");
  ClipSet s = ThreeClips();
  fs::create_directories(fs::path(dir) / "clip_000");
  fs::create_directory_symlink(outside, fs::path(dir) / "clip_001");
  absl::StatusOr<std::string> ok = ClipPath(dir, s.clips[0]);
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_EQ(*ok, (fs::path(dir) / "clip_000").string());
  EXPECT_EQ(ClipPath(dir, s.clips[1]).status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(ClipPath(dir, s.clips[2]).status().code(), absl::StatusCode::kNotFound);  // missing
  // SceneDirForTime: a plain directory is itself; a clip set gives the clip of the time.
  absl::StatusOr<std::string> plain = SceneDirForTime(dir, 5);
  ASSERT_TRUE(plain.ok());
  EXPECT_EQ(*plain, dir);
  ASSERT_TRUE(WriteClipSet(s, dir).ok());
  absl::StatusOr<std::string> first = SceneDirForTime(dir, std::nullopt);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(*first, (fs::path(dir) / "clip_000").string());
  EXPECT_FALSE(SceneDirForTime(dir, 1'000'000).ok());  // clip_001 leaves the set
}

TEST(ClipPick, InsideBetweenAndOutside) {
  const ClipSet s = ThreeClips();  // [0, 0.7 s], [0.8, 1.5 s], [1.6, 1.9 s]
  EXPECT_EQ(PickClip(s, 0), 0);
  EXPECT_EQ(PickClip(s, 700'000), 0);
  EXPECT_EQ(PickClip(s, 800'000), 1);
  EXPECT_EQ(PickClip(s, 1'500'000), 1);
  EXPECT_EQ(PickClip(s, 1'700'000), 2);
  EXPECT_EQ(PickClip(s, 740'000), 0);    // between: nearer clip
  EXPECT_EQ(PickClip(s, 760'000), 1);
  EXPECT_EQ(PickClip(s, 750'000), 0);    // tie: the earlier
  EXPECT_EQ(PickClip(s, -5'000'000), 0);  // before the log
  EXPECT_EQ(PickClip(s, 9'000'000), 2);   // after it
  EXPECT_EQ(PickClip(s, INT64_MIN), 0);
  EXPECT_EQ(PickClip(s, INT64_MAX), 2);
}

TEST(ClipMerge, MeansOverTheFramesWhereDefined) {
  EvalResult a, b;
  FrameMetrics f;
  f.psnr = 20, f.ssim = 0.5, f.depth_median_abs_m = 1.0, f.depth_within_5pct = 0.2, f.psnr_dynamic = 15;
  a.frames.push_back(f);
  f.psnr = 30, f.ssim = 0.7, f.depth_median_abs_m = -1, f.depth_within_5pct = -1, f.psnr_dynamic = -1;
  f.psnr_static = 31;
  b.frames.push_back(f);
  const EvalResult m = MergeEvalResults({a, b});
  ASSERT_EQ(m.frames.size(), 2u);
  EXPECT_DOUBLE_EQ(m.mean.psnr, 25);
  EXPECT_DOUBLE_EQ(m.mean.ssim, 0.6);
  EXPECT_DOUBLE_EQ(m.mean.depth_median_abs_m, 1.0);
  EXPECT_DOUBLE_EQ(m.mean.psnr_dynamic, 15);
  EXPECT_DOUBLE_EQ(m.mean.psnr_static, 31);
  LidarEvalResult la, lb;
  LidarFrameMetrics l;
  l.frame = 3, l.chamfer_m = 2, l.range_median_abs_m = -1, l.rays = 10;
  la.frames.push_back(l);
  l.frame = 11, l.chamfer_m = 4, l.range_median_abs_m = 0.5, l.rays = 5;
  lb.frames.push_back(l);
  const LidarEvalResult lm = MergeLidarEvalResults({la, lb});
  EXPECT_DOUBLE_EQ(lm.mean.chamfer_m, 3);
  EXPECT_DOUBLE_EQ(lm.mean.range_median_abs_m, 0.5);
  EXPECT_EQ(lm.mean.rays, 15u);
  EXPECT_DOUBLE_EQ(lm.mean.drop_accuracy, -1);
}

// 19 frames of the KITTI clip, two clips of 8 + 11 frames, a tiny field whose learning rates are
// ~0 so that a field's parameters show where they started.
TrainOptions TinyOptions() {
  TrainOptions o;
  o.iterations = 6;
  o.resolution_scale = 0.12;
  o.holdout_every = 4;
  o.seed = 3;
  o.deterministic = true;
  o.checkpoint_every = 2;
  o.init_voxel_m = 0.5;
  o.lidar_weight = 0;
  o.field.mode = FieldMode::kS3Gaussian;
  o.field.static_iterations = 3;
  o.field.config.channels = 4;
  o.field.config.base_resolution = 8;
  o.field.config.multires = {1, 2};
  o.field.config.time_resolution = 6;
  o.field.config.width = 16;
  o.field.hyper.grid_lr_init = o.field.hyper.grid_lr_final = 1e-30;
  o.field.hyper.deformation_lr_init = o.field.hyper.deformation_lr_final = 1e-30;
  return o;
}

DriveLog ShortLog() {
  absl::StatusOr<DriveLog> log = OpenLog(kKitti);
  EXPECT_TRUE(log.ok()) << log.status();
  log->frames.resize(19);
  return *log;
}

double MaxAbsDiff(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  double d = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) d = std::max(d, std::abs(double(a[i]) - b[i]));
  return d;
}

// A two-clip run of `opt` killed in clip 1 at iteration `stop_after` (as if killed).
absl::StatusOr<ClipTrainResult> KilledInClip1(const DriveLog& log, const std::string& dir, const TrainOptions& opt,
                                              const ClipTrainOptions& copt, int stop_after) {
  TrainOptions killed = opt;
  killed.stop_after = stop_after;
  ClipTrainOptions kcopt = copt;
  kcopt.stop_in_clip = 1;
  return TrainClips(log, dir, killed, kcopt);
}

TEST(ClipTraining, PriorFieldAndResumeInTheClipItWasKilledIn) {
  const DriveLog log = ShortLog();
  const TrainOptions opt = TinyOptions();
  ClipTrainOptions copt;
  copt.clip_frames = 8;

  // Uninterrupted.
  const std::string a = TempDir("train_a");
  absl::StatusOr<ClipTrainResult> ra = TrainClips(log, a, opt, copt);
  ASSERT_TRUE(ra.ok()) << ra.status();
  ASSERT_TRUE(ra->set.has_value());
  ASSERT_EQ(ra->runs.size(), 2u);
  EXPECT_FALSE(ra->stopped);
  absl::StatusOr<std::optional<ClipSet>> set = ReadClipSet(a);
  ASSERT_TRUE(set.ok() && set->has_value());
  ASSERT_EQ((*set)->clips.size(), 2u);
  EXPECT_TRUE((*set)->clips[0].done && (*set)->clips[1].done);
  EXPECT_EQ((*set)->clips[1].frames, (ClipRange{8, 19}));
  EXPECT_EQ((*set)->clips[1].start_us, log.frames[8].time_us);
  EXPECT_EQ((*set)->clips[1].end_us, log.frames[18].time_us);
  for (const char* f : {"scene.ply", "field.bin", "train_meta.json", "checkpoint.bin", "scene.json"}) {
    EXPECT_TRUE(fs::exists(fs::path(a) / "clip_001" / f)) << f;
  }
  // Held-out views by the log's frame index: clip 1 holds out 11 and 15 (not 8 + 3 = 11, 8 + 7).
  ASSERT_EQ(ra->runs[1].result.heldout.frames.size(), 2u);
  EXPECT_EQ(ra->runs[1].result.heldout.frames[0].frame, 11);
  EXPECT_EQ(ra->runs[1].result.heldout.frames[1].frame, 15);
  ASSERT_EQ(ra->runs[0].result.heldout.frames.size(), 2u);
  EXPECT_EQ(ra->runs[0].result.heldout.frames[0].frame, 3);

  // Clip 1's field: clip 0's parameters (learning rates ~0), over its own AABB and times.
  absl::StatusOr<field::DeformationField> f0 = field::LoadField((fs::path(a) / "clip_000/field.bin").string());
  absl::StatusOr<field::DeformationField> f1 = field::LoadField((fs::path(a) / "clip_001/field.bin").string());
  ASSERT_TRUE(f0.ok() && f1.ok());
  EXPECT_LT(MaxAbsDiff(f0->params(), f1->params()), 1e-12);
  EXPECT_EQ(f1->time_range().start_us, log.frames[8].time_us);
  EXPECT_EQ(f1->time_range().end_us, log.frames[18].time_us);
  EXPECT_EQ(f0->time_range().end_us, log.frames[7].time_us);
  EXPECT_NE(f0->aabb().min[0], f1->aabb().min[0]);
  // What a fresh field of clip 1 would have been (its seed is seed + 1): far from clip 0's.
  absl::StatusOr<field::DeformationField> fresh =
      field::DeformationField::Create(opt.field.config, f1->aabb(), f1->time_range(), opt.seed + 1);
  ASSERT_TRUE(fresh.ok());
  EXPECT_GT(MaxAbsDiff(fresh->params(), f1->params()), 1e-3);

  // Killed in clip 1 after its checkpoint at 4 (one fine iteration in), then resumed.
  const std::string b = TempDir("train_b");
  absl::StatusOr<ClipTrainResult> rb = KilledInClip1(log, b, opt, copt, 5);
  ASSERT_TRUE(rb.ok()) << rb.status();
  EXPECT_TRUE(rb->stopped);
  ASSERT_EQ(rb->runs.size(), 2u);
  EXPECT_EQ(rb->runs[1].result.iterations, 5);
  set = ReadClipSet(b);
  ASSERT_TRUE(set.ok() && set->has_value());
  EXPECT_TRUE((*set)->clips[0].done);
  EXPECT_FALSE((*set)->clips[1].done);
  const fs::path clip0_ply = fs::path(b) / "clip_000/scene.ply";
  const auto clip0_time = fs::last_write_time(clip0_ply);

  TrainOptions resumed = opt;
  resumed.resume = true;
  int64_t first_iteration = -1;
  absl::StatusOr<ClipTrainResult> rc = TrainClips(log, b, resumed, copt, [&](const Progress& p) {
    if (first_iteration < 0) first_iteration = p.iteration;
  });
  ASSERT_TRUE(rc.ok()) << rc.status();
  EXPECT_EQ(first_iteration, 5);  // continued from clip 1's checkpoint at 4
  ASSERT_EQ(rc->runs.size(), 1u);  // clip 0 is done: not retrained
  EXPECT_EQ(rc->runs[0].clip, 1);
  EXPECT_EQ(rc->runs[0].result.iterations, 6);
  EXPECT_EQ(fs::last_write_time(clip0_ply), clip0_time);
  set = ReadClipSet(b);
  ASSERT_TRUE(set.ok() && set->has_value());
  EXPECT_TRUE((*set)->clips[1].done);
  // The resumed clip 1 ends where the uninterrupted one did (fine stage: to float noise,
  // docs/training.md "Dynamic field").
  absl::StatusOr<GaussianStore> ga = ReadGaussianPly((fs::path(a) / "clip_001/scene.ply").string());
  absl::StatusOr<GaussianStore> gb = ReadGaussianPly((fs::path(b) / "clip_001/scene.ply").string());
  ASSERT_TRUE(ga.ok() && gb.ok());
  ASSERT_EQ(ga->size(), gb->size());
  EXPECT_LT(MaxAbsDiff(ga->means, gb->means), 1e-5);
  EXPECT_LT(MaxAbsDiff(ga->sh, gb->sh), 1e-5);

  // Everything done: a resume trains nothing; another plan or a plain resume is refused.
  absl::StatusOr<ClipTrainResult> rd = TrainClips(log, b, resumed, copt);
  ASSERT_TRUE(rd.ok()) << rd.status();
  EXPECT_TRUE(rd->runs.empty());
  ClipTrainOptions other = copt;
  other.clip_frames = 6;
  EXPECT_EQ(TrainClips(log, b, resumed, other).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(TrainClips(log, b, resumed, ClipTrainOptions{}).status().code(), absl::StatusCode::kFailedPrecondition);
}

// --clip-overlap: each clip trains on its neighbour's frames next to the switch (the views, the
// field's time axis, the clip's scene.json) and serves / is evaluated on its own frames.
TEST(ClipTraining, OverlapTrainsOnTheNeighboursFrames) {
  const DriveLog log = ShortLog();
  const TrainOptions opt = TinyOptions();
  ClipTrainOptions copt;
  copt.clip_frames = 8;
  copt.overlap_frames = 2;
  const std::string a = TempDir("overlap_train");
  absl::StatusOr<ClipTrainResult> ra = TrainClips(log, a, opt, copt);
  ASSERT_TRUE(ra.ok()) << ra.status();
  ASSERT_EQ(ra->runs.size(), 2u);
  EXPECT_EQ(ra->runs[0].trained, (ClipRange{0, 10}));
  EXPECT_EQ(ra->runs[1].trained, (ClipRange{6, 19}));
  EXPECT_EQ(ra->runs[1].frames, (ClipRange{8, 19}));
  // Held out by the log-wide rule over the trained frames: clip 0 holds out 3 and 7, clip 1 the
  // overlap frame 7 as well as its own 11 and 15.
  std::vector<int> held0, held1;
  for (const FrameMetrics& m : ra->runs[0].result.heldout.frames) held0.push_back(m.frame);
  for (const FrameMetrics& m : ra->runs[1].result.heldout.frames) held1.push_back(m.frame);
  EXPECT_EQ(held0, (std::vector<int>{3, 7}));
  EXPECT_EQ(held1, (std::vector<int>{7, 11, 15}));
  absl::StatusOr<field::DeformationField> f0 = field::LoadField((fs::path(a) / "clip_000/field.bin").string());
  absl::StatusOr<field::DeformationField> f1 = field::LoadField((fs::path(a) / "clip_001/field.bin").string());
  ASSERT_TRUE(f0.ok() && f1.ok());
  EXPECT_EQ(f0->time_range().end_us, log.frames[9].time_us);
  EXPECT_EQ(f1->time_range().start_us, log.frames[6].time_us);
  EXPECT_EQ(f1->time_range().end_us, log.frames[18].time_us);
  absl::StatusOr<std::optional<ClipSet>> set = ReadClipSet(a);
  ASSERT_TRUE(set.ok() && set->has_value());
  EXPECT_EQ((*set)->overlap_frames, 2);
  EXPECT_EQ((*set)->clips[1].start_us, log.frames[8].time_us);  // PickClip's ranges: its own frames
  EXPECT_EQ((*set)->clips[0].end_us, log.frames[7].time_us);
  // A resume with another overlap is another plan.
  TrainOptions resumed = opt;
  resumed.resume = true;
  ClipTrainOptions other = copt;
  other.overlap_frames = 1;
  absl::StatusOr<ClipTrainResult> rb = TrainClips(log, a, resumed, other);
  EXPECT_EQ(rb.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(rb.status().message().find("overlap"), std::string::npos) << rb.status();
  other.overlap_frames = 5;  // above half a clip
  EXPECT_EQ(TrainClips(log, a, resumed, other).status().code(), absl::StatusCode::kInvalidArgument);

  // Seams: clip 0 and clip 1 render frames 7 and 8 (1 camera each); a copy of clip 0 in place of
  // clip 1 makes the seam vanish (identical renders), which the trained clip 1 does not.
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(engine.ok());
  absl::StatusOr<std::vector<ClipSeam>> seams =
      MeasureClipSeams(**engine, a, **set, log, opt.resolution_scale);
  ASSERT_TRUE(seams.ok()) << seams.status();
  ASSERT_EQ(seams->size(), 1u);
  EXPECT_EQ((*seams)[0].frames, (std::vector<int>{7, 8}));
  EXPECT_EQ((*seams)[0].views, 2u);
  EXPECT_GT((*seams)[0].switch_time_us, log.frames[7].time_us);
  EXPECT_LE((*seams)[0].switch_time_us, log.frames[8].time_us);
  EXPECT_EQ(PickClip(**set, (*seams)[0].switch_time_us), 1);
  EXPECT_EQ(PickClip(**set, (*seams)[0].switch_time_us - 1), 0);
  EXPECT_LT((*seams)[0].psnr_between_db, 60);
  EXPECT_GT((*seams)[0].psnr_before_db, 5);
  fs::remove_all(fs::path(a) / "clip_001");
  fs::copy(fs::path(a) / "clip_000", fs::path(a) / "clip_001", fs::copy_options::recursive);
  seams = MeasureClipSeams(**engine, a, **set, log, opt.resolution_scale);
  ASSERT_TRUE(seams.ok()) << seams.status();
  EXPECT_EQ((*seams)[0].psnr_between_db, 100);  // Psnr's value for identical images
  EXPECT_DOUBLE_EQ((*seams)[0].psnr_before_db, (*seams)[0].psnr_after_db);
  // The meter behind it (streetsim eval feeds it the scenes it loads): clips in order, each once,
  // and no seams before every clip was given.
  absl::StatusOr<ClipSeamMeter> meter = ClipSeamMeter::Create(**set, log, opt.resolution_scale);
  ASSERT_TRUE(meter.ok()) << meter.status();
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> field0 = LoadSceneField((fs::path(a) / "clip_000").string());
  absl::StatusOr<GaussianStore> store0 = ReadGaussianPly((fs::path(a) / "clip_000" / "scene.ply").string());
  ASSERT_TRUE(field0.ok() && store0.ok());
  absl::StatusOr<SceneForView> sv0 = MakeSceneForView(**engine, *store0, *field0);
  ASSERT_TRUE(sv0.ok());
  const Eigen::Vector3f grey(0.5f, 0.5f, 0.5f);
  EXPECT_EQ(meter->AddClip(**engine, 1, *sv0, grey).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(meter->AddClip(**engine, 0, *sv0, grey).ok());
  EXPECT_EQ(meter->AddClip(**engine, 0, *sv0, grey).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(meter->Finish().status().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(meter->AddClip(**engine, 1, *sv0, grey).ok());
  EXPECT_EQ(meter->AddClip(**engine, 2, *sv0, grey).code(), absl::StatusCode::kFailedPrecondition);
  absl::StatusOr<std::vector<ClipSeam>> same = meter->Finish();
  ASSERT_TRUE(same.ok()) << same.status();
  EXPECT_EQ((*same)[0].psnr_between_db, 100);  // one scene on both sides
  // A missing clip directory is an error, not a crash.
  fs::remove_all(fs::path(a) / "clip_001");
  EXPECT_FALSE(MeasureClipSeams(**engine, a, **set, log, opt.resolution_scale).ok());
}

// --field extended: clip 1's extension starts from clip 0's field_ext.bin (and its base from
// clip 0's field.bin), and a run killed in clip 1's fine stage resumes to the same bits.
TEST(ClipTraining, ExtendedFieldChainsAndResumesInClip1) {
  const DriveLog log = ShortLog();
  TrainOptions opt = TinyOptions();
  opt.field.extended = field::ExtendedFieldConfig::AllOn();  // small sizes, every module
  opt.field.extended->vae_dilation = 1;
  ClipTrainOptions copt;
  copt.clip_frames = 8;
  auto ext_of = [](const std::string& clip_dir) {
    const fs::path d(clip_dir);
    absl::StatusOr<field::DeformationField> base = field::LoadField((d / field::kFieldFileName).string());
    EXPECT_TRUE(base.ok()) << base.status();
    absl::StatusOr<field::ExtendedField> ext =
        field::LoadExtendedField((d / field::kExtendedFieldFileName).string(), std::move(*base));
    EXPECT_TRUE(ext.ok()) << ext.status();
    return ext->params();
  };

  const std::string a = TempDir("ext_a");
  absl::StatusOr<ClipTrainResult> ra = TrainClips(log, a, opt, copt);
  ASSERT_TRUE(ra.ok()) << ra.status();
  ASSERT_EQ(ra->runs.size(), 2u);
  const std::vector<float> e0 = ext_of((fs::path(a) / "clip_000").string());
  const std::vector<float> e1 = ext_of((fs::path(a) / "clip_001").string());
  ASSERT_EQ(e0.size(), e1.size());
  // 3 fine iterations of Adam at the network rate 1.6e-3 move a parameter by about 5e-3; clip 1's
  // own init (seed + 1) differs from clip 0's parameters by O(0.1-1) (Xavier weights).
  EXPECT_LT(MaxAbsDiff(e0, e1), 0.02);
  EXPECT_GT(MaxAbsDiff(e0, e1), 0);  // and clip 1 did train it

  // Killed in clip 1 after its checkpoint at 4 (one fine iteration in), resumed: the same bits.
  const std::string b = TempDir("ext_b");
  absl::StatusOr<ClipTrainResult> rb = KilledInClip1(log, b, opt, copt, 5);
  ASSERT_TRUE(rb.ok()) << rb.status();
  ASSERT_TRUE(rb->stopped);
  TrainOptions resumed = opt;
  resumed.resume = true;
  absl::StatusOr<ClipTrainResult> rc = TrainClips(log, b, resumed, copt);
  ASSERT_TRUE(rc.ok()) << rc.status();
  ASSERT_EQ(rc->runs.size(), 1u);
  EXPECT_EQ(ext_of((fs::path(b) / "clip_001").string()), e1);
  absl::StatusOr<GaussianStore> ga = ReadGaussianPly((fs::path(a) / "clip_001/scene.ply").string());
  absl::StatusOr<GaussianStore> gb = ReadGaussianPly((fs::path(b) / "clip_001/scene.ply").string());
  ASSERT_TRUE(ga.ok() && gb.ok());
  EXPECT_EQ(ga->means, gb->means);
  EXPECT_EQ(ga->sh, gb->sh);

  // Another module list than clip 0's extension: refused with the reason (a resume across clips
  // with other modules, clip 1 not started: its checkpoint is gone).
  const std::string c = TempDir("ext_c");
  ASSERT_TRUE(KilledInClip1(log, c, opt, copt, 2).ok());  // clip 1 stopped in its static stage
  TrainOptions other = resumed;
  other.field.extended->vae_dilation = 0;
  absl::StatusOr<ClipTrainResult> rd = TrainClips(log, c, other, copt);
  ASSERT_FALSE(rd.ok());
  EXPECT_NE(rd.status().message().find("does not match"), std::string::npos) << rd.status();
}

}  // namespace
}  // namespace streetsim::train
