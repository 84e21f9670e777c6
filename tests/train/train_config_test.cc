// The training settings (scene/train/config/): the one table, values from text, JSON and config
// files, presets and their schedules, a run's config.json and what a resume changes, and the
// migration of directories from before config.json. The CLI's exit codes: cli_train_test.cc.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <set>

#include <nlohmann/json.hpp>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "scene/log/colmap_reader.h"
#include "scene/train/config/run_config.h"
#include "scene/train/config/run_resolution.h"
#include "scene/train/config/train_settings.h"
#include "scene/train/stage_history.h"
#include "tests/common/scratch_dir.h"

namespace streetsim::train::config {
namespace {

bool Has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

CommandLineConfig Given(std::vector<std::pair<std::string, std::string>> values) {
  CommandLineConfig c;
  for (auto& [n, v] : values) c.values.push_back({n, v, "--" + n});
  return c;
}

TEST(TrainSettings, EveryDeclarationIsWholeAndItsDefaultValid) {
  std::set<std::string> names;
  for (const SettingDef& d : TrainSettingDefs()) {
    EXPECT_TRUE(names.insert(d.name).second) << d.name << " declared twice";
    EXPECT_GT(std::string(d.help).size(), 10u) << d.name;
    Settings s = DefaultTrainSettings();
    EXPECT_TRUE(s.Set(d.name, d.default_value, Origin::kGiven, "test").ok()) << d.name;
  }
  EXPECT_GE(names.size(), 40u);
  // The defaults alone resolve (a static 30000-iteration run with the old trainer's defaults).
  absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(DefaultTrainSettings());
  ASSERT_TRUE(o.ok()) << o.status();
  EXPECT_EQ(o->train.iterations, 30000);
  EXPECT_EQ(o->train.field.mode, FieldMode::kS3Gaussian);  // auto: longer than the static stage
  EXPECT_DOUBLE_EQ(o->train.field.hyper.lr_scale, 10);
}

TEST(TrainSettings, ValuesAreCheckedByTheirDeclaration) {
  Settings s = DefaultTrainSettings();
  EXPECT_TRUE(s.SetText("iterations", "12", Origin::kGiven, "--iterations").ok());
  EXPECT_EQ(s.GetInt("iterations"), 12);
  EXPECT_TRUE(s.SetText("pose-refinement", "true", Origin::kGiven, "--set pose-refinement").ok());
  EXPECT_TRUE(s.GetBool("pose-refinement"));
  EXPECT_TRUE(s.SetText("field-lr-scale", "2", Origin::kGiven, "x").ok());
  EXPECT_DOUBLE_EQ(s.GetDouble("field-lr-scale"), 2);
  struct Case {
    std::string name, text, message;
  };
  for (const Case& c : std::vector<Case>{
           {"iterations", "0", "--iterations: iterations must be an integer in 1..10000000, not '0'"},
           {"iterations", "many", "iterations must be an integer in 1..10000000, not 'many'"},
           {"iterations", "1.5", "not '1.5'"},
           {"resolution-scale", "0", "resolution-scale must be a number in (0, 1], not '0'"},
           {"resolution-scale", "nan", "not 'nan'"},
           {"field", "dynamic", "field must be one of auto, static, s3gaussian, extended, not 'dynamic'"},
           {"pose-refinement", "yes", "pose-refinement must be true or false, not 'yes'"},
           {"field-modules", "warp", "field-modules: "},
           {"bogus", "1", "unknown setting 'bogus'"},
           {"bad\x01name", "1", "unknown setting 'bad?name'"}}) {
    const absl::Status st = s.SetText(c.name, c.text, Origin::kGiven, "--" + c.name);
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << c.name;
    EXPECT_TRUE(Has(std::string(st.message()), c.message)) << st.message();
  }
  EXPECT_EQ(s.GetInt("iterations"), 12) << "a refused value leaves the old one";
  // JSON: types are the declaration's (an integer setting takes no fraction, a bool no number).
  EXPECT_TRUE(s.SetJson("iterations", nlohmann::json(40), Origin::kGiven, "f").ok());
  EXPECT_FALSE(s.SetJson("iterations", nlohmann::json(4.5), Origin::kGiven, "f").ok());
  EXPECT_FALSE(s.SetJson("iterations", nlohmann::json("40"), Origin::kGiven, "f").ok());
  EXPECT_FALSE(s.SetJson("exposure", nlohmann::json(1), Origin::kGiven, "f").ok());
  EXPECT_TRUE(s.SetJson("field-lr-scale", nlohmann::json(3), Origin::kGiven, "f").ok());
}

TEST(TrainSettings, RelationsBetweenGivenSettingsAreChecked) {
  auto resolve = [](std::vector<std::pair<std::string, std::string>> values) {
    Settings s = DefaultTrainSettings();
    for (auto& [n, v] : values) EXPECT_TRUE(s.SetText(n, v, Origin::kGiven, n).ok()) << n;
    return ResolveTrainOptions(s).status();
  };
  EXPECT_TRUE(Has(std::string(resolve({{"field", "static"}, {"field-lr-scale", "2"}}).message()),
                  "field-lr-scale needs a field"));
  EXPECT_TRUE(Has(std::string(resolve({{"iterations", "100"}, {"field", "s3gaussian"}}).message()),
                  "static-iterations (5000) must be below iterations (100)"));
  EXPECT_TRUE(Has(std::string(resolve({{"pose-refine-from", "3"}}).message()), "needs pose-refinement"));
  EXPECT_TRUE(Has(std::string(resolve({{"field-modules", "vae"}}).message()), "needs field extended"));
  EXPECT_TRUE(Has(std::string(resolve({{"holdout-every", "1"}}).message()), "holdout-every"));
  EXPECT_TRUE(Has(std::string(resolve({{"clip-overlap", "2"}}).message()), "clip-overlap needs clip-frames"));
  EXPECT_TRUE(resolve({{"iterations", "100"}, {"field", "static"}, {"pose-refinement", "true"}}).ok());
  // A field run freezes its refined poses at the static stage's end unless told.
  Settings s = DefaultTrainSettings();
  ASSERT_TRUE(s.SetText("pose-refinement", "true", Origin::kGiven, "x").ok());
  absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(s);
  ASSERT_TRUE(o.ok());
  EXPECT_EQ(o->train.hyper.pose_refine_until, 5000);
}

// The quality preset is the former scripts/kitti-recipe's run (docs/benchmarks.md, 27.05 dB): the
// same segment ends (where that script's runs wrote their outputs) and the same flags in each,
// then its last stage's settings for 1500 iterations more (docs/benchmarks.md "`quality`").
TEST(Presets, QualityIsTheRecipesSegmentsRunLonger) {
  absl::StatusOr<RunConfig> q = PresetConfig("quality");
  ASSERT_TRUE(q.ok()) << q.status();
  const std::vector<Segment> segments = Segments(*q);
  std::vector<int64_t> ends;
  for (const Segment& s : segments) ends.push_back(s.end);
  EXPECT_EQ(ends, (std::vector<int64_t>{5000, 6010, 7510, 8010, 8510, 9010, 9510, 10010, 10510, 11010, 11510, 12010,
                                        12510, 13010, 13510, 14010}));
  for (const Segment& s : segments) {
    absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(s.settings, s.end);
    ASSERT_TRUE(o.ok()) << s.end << ": " << o.status();
    const TrainOptions& t = o->train;
    EXPECT_EQ(t.iterations, s.end);
    EXPECT_EQ(t.holdout_every, 4);
    EXPECT_EQ(t.checkpoint_every, 250);
    EXPECT_TRUE(t.pose_refinement);
    EXPECT_EQ(t.hyper.pose_refine_from, 300);
    EXPECT_EQ(t.hyper.pose_refine_until, 5000);
    EXPECT_DOUBLE_EQ(t.resolution_scale, 1.0);
    if (s.end == 5000) {  // `--field static --iterations 5000`
      EXPECT_EQ(t.field.mode, FieldMode::kStatic);
      continue;
    }
    EXPECT_EQ(t.field.mode, FieldMode::kS3Gaussian);
    EXPECT_EQ(t.field.static_iterations, 5000);
    EXPECT_DOUBLE_EQ(t.motion_prior.weight, 0.3);
    EXPECT_DOUBLE_EQ(t.field.hyper.lr_scale, 10);
    EXPECT_EQ(t.field.hyper.lr_decay_steps, s.end <= 7510 ? 30000 : 4500) << s.end;
    EXPECT_EQ(t.hyper.densify_until, s.end <= 10010 ? 25000 : 5000) << s.end;
    EXPECT_EQ(t.hyper.lr_decay_steps, 30000) << s.end;
  }
  absl::StatusOr<RunConfig> p = PresetConfig("preview");
  ASSERT_TRUE(p.ok());
  ASSERT_EQ(Segments(*p).size(), 1u);
  absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(Segments(*p)[0].settings);
  ASSERT_TRUE(o.ok());
  EXPECT_EQ(o->train.iterations, 1700);
  EXPECT_EQ(o->train.field.static_iterations, 1000);
  EXPECT_EQ(o->train.field.mode, FieldMode::kS3Gaussian);
  EXPECT_FALSE(PresetDescription("preview").empty());
  const absl::Status unknown = PresetConfig("best").status();
  EXPECT_EQ(unknown.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(Has(std::string(unknown.message()), "no preset 'best' (presets: quality, preview)")) << unknown;
}

TEST(RunConfigFiles, DocumentsAreCheckedWholeAndNameTheirSource) {
  struct Case {
    std::string text, message;
  };
  for (const Case& c : std::vector<Case>{
           {"{", "my.json is not valid JSON"},
           {"[1]", "must hold a JSON object"},
           {R"({"schema_version": 2})", "schema_version 2, newer than this streetsim's 1"},
           {R"({"schema_version": "1"})", "schema_version must be an integer"},
           {R"({"setings": {}})", "unknown key 'setings'"},
           {R"({"settings": {"iterations": -4}})", "my.json: iterations must be an integer in 1..10000000"},
           {R"({"settings": {"warp": 1}})", "unknown setting 'warp'"},
           {R"({"schedule": [{"from": 10}, {"from": 5}]})", "increasing"},
           {R"({"schedule": [{"from": 0, "set": {"field": "x"}}]})", "schedule[0]: field must be one of"},
           {R"({"schedule": [{"from": 0, "when": 1}]})", "unknown key 'when'"}}) {
    RunConfig config;
    const absl::Status s = ApplyConfigDocument(c.text, Origin::kGiven, "my.json", &config);
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << c.text;
    EXPECT_TRUE(Has(std::string(s.message()), c.message)) << c.text << ": " << s.message();
  }
  RunConfig config;
  ASSERT_TRUE(ApplyConfigDocument(R"({"settings": {"iterations": 900}, "schedule": [{"from": 300,
      "set": {"densify-until": 10}}]})", Origin::kGiven, "f", &config).ok());
  ASSERT_EQ(config.schedule.size(), 2u) << "a first stage from 0 is implied";
  const std::vector<Segment> s = Segments(config);
  ASSERT_EQ(s.size(), 2u);
  EXPECT_EQ(s[0].end, 300);
  EXPECT_EQ(s[1].end, 900);
  EXPECT_EQ(s[0].settings.GetInt("densify-until"), 25000);
  EXPECT_EQ(s[1].settings.GetInt("densify-until"), 10);
}

TEST(RunConfigFiles, ConfigJsonRoundTripsAndRefusesDamage) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "roundtrip");
  EXPECT_TRUE(absl::IsNotFound(ReadRunConfig(dir).status()));
  absl::StatusOr<RunConfig> q = PresetConfig("quality");
  ASSERT_TRUE(q.ok());
  ASSERT_TRUE(q->settings.SetText("seed", "7", Origin::kGiven, "--seed").ok());
  ASSERT_TRUE(WriteRunConfig(dir, *q).ok());
  absl::StatusOr<RunConfig> back = ReadRunConfig(dir);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(RunConfigJson(*back), RunConfigJson(*q));
  EXPECT_TRUE(back->settings.given("seed"));
  EXPECT_FALSE(back->settings.given("iterations"));
  const std::string path = dir + "/config.json";
  const std::string whole = RunConfigJson(*q);
  std::ofstream(path, std::ios::trunc) << whole.substr(0, whole.size() / 2);
  absl::Status s = ReadRunConfig(dir).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss) << s;
  EXPECT_TRUE(Has(std::string(s.message()), path)) << s;
  nlohmann::json future = nlohmann::json::parse(whole);
  future["schema_version"] = 9;
  std::ofstream(path, std::ios::trunc) << future.dump();
  s = ReadRunConfig(dir).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << s;
  EXPECT_TRUE(Has(std::string(s.message()), "schema_version 9")) << s;
}

// `field auto` on a log without LiDAR trains the static model (measured on both shared
// camera-only logs); what the user asked for, a log with LiDAR and a resume keep the field.
TEST(RunResolution, FieldAutoOnACameraOnlyLogIsTheStaticModel) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "camera_only");
  DriveLog camera_only, with_lidar;
  with_lidar.lidars.emplace_back();
  for (const char* preset : {"quality", "preview"}) {
    CommandLineConfig given;
    given.preset = preset;
    absl::StatusOr<ResolvedRun> run = ResolveRun(dir, false, given);
    ASSERT_TRUE(run.ok()) << run.status();
    ASSERT_TRUE(FitFieldToLog(with_lidar, &*run).ok());
    EXPECT_EQ(run->config.settings.GetText("field"), "s3gaussian") << preset;
    EXPECT_TRUE(run->config.notes.empty());
    run = ResolveRun(dir, false, given);
    ASSERT_TRUE(FitFieldToLog(camera_only, &*run).ok());
    EXPECT_EQ(run->config.settings.GetText("field"), "static") << preset;
    for (const Segment& s : Segments(run->config)) {
      absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(s.settings, s.end);
      ASSERT_TRUE(o.ok()) << o.status();
      EXPECT_EQ(o->train.field.mode, FieldMode::kStatic);
    }
    ASSERT_EQ(run->config.notes.size(), 1u);
    EXPECT_EQ(run->config.notes[0], kCameraOnlyStaticNote);
    // Once is enough: a second call (a retried job) changes nothing more.
    ASSERT_TRUE(FitFieldToLog(camera_only, &*run).ok());
    EXPECT_EQ(run->config.notes.size(), 1u);
  }
  // Asked for, by name or by a field's setting: the field, camera-only or not.
  for (const auto& g : {Given({{"field", "s3gaussian"}}), Given({{"static-iterations", "700"}, {"iterations", "1300"}}),
                        Given({{"field-lr-scale", "3"}})}) {
    absl::StatusOr<ResolvedRun> run = ResolveRun(dir, false, g);
    ASSERT_TRUE(run.ok()) << run.status();
    ASSERT_TRUE(FitFieldToLog(camera_only, &*run).ok());
    EXPECT_EQ(run->config.settings.GetText("field"), "s3gaussian") << g.values[0].name;
    EXPECT_TRUE(run->config.notes.empty());
  }
  // A resume keeps its recorded field.
  absl::StatusOr<ResolvedRun> run = ResolveRun(dir, false, CommandLineConfig{});
  ASSERT_TRUE(run.ok());
  ASSERT_TRUE(WriteRunConfig(dir, run->config).ok());
  run = ResolveRun(dir, true, CommandLineConfig{});
  ASSERT_TRUE(run.ok()) << run.status();
  ASSERT_TRUE(FitFieldToLog(camera_only, &*run).ok());
  EXPECT_EQ(run->config.settings.GetText("field"), "s3gaussian");
}

// The preset's pose refinement is left out on a log whose poses came from its own images (COLMAP:
// refined, colmap_plush's held-out views lost 1.2-1.9 dB); recorded poses (GNSS/INS, the odometry
// excerpt's) are refined, LiDAR or not; a pose setting the user gave and a resume keep theirs.
TEST(RunResolution, ThePresetsPoseRefinementIsOffForPosesFromTheImages) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "image_poses");
  DriveLog colmap, odometry, with_lidar;
  colmap.pose_source = kColmapPoseSource;
  odometry.pose_source = "poses.txt";
  with_lidar.pose_source = "oxts";
  with_lidar.lidars.emplace_back();
  auto refines = [](const ResolvedRun& run) {
    std::vector<bool> r;
    for (const Segment& s : Segments(run.config)) {
      absl::StatusOr<TrainRunOptions> o = ResolveTrainOptions(s.settings, s.end);
      EXPECT_TRUE(o.ok()) << o.status();
      r.push_back(o.ok() && o->train.pose_refinement);
    }
    return r;
  };
  auto has_note = [](const ResolvedRun& run) {
    return std::count(run.config.notes.begin(), run.config.notes.end(), std::string(kImagePosesNote));
  };
  absl::StatusOr<ResolvedRun> run = ResolveRun(dir, false, CommandLineConfig{});
  ASSERT_TRUE(run.ok()) << run.status();
  for (const DriveLog* recorded : {&with_lidar, &odometry}) {
    ASSERT_TRUE(FitFieldToLog(*recorded, &*run).ok());
    absl::StatusOr<bool> off = FitPosesToLog(*recorded, &*run);
    ASSERT_TRUE(off.ok()) << off.status();
    EXPECT_FALSE(*off) << recorded->pose_source;
    EXPECT_THAT(refines(*run), ::testing::Each(true)) << recorded->pose_source;
    EXPECT_EQ(has_note(*run), 0);
  }

  run = ResolveRun(dir, false, CommandLineConfig{});
  ASSERT_TRUE(run.ok()) << run.status();
  ASSERT_TRUE(FitFieldToLog(colmap, &*run).ok());
  absl::StatusOr<bool> off = FitPosesToLog(colmap, &*run);
  ASSERT_TRUE(off.ok()) << off.status();
  EXPECT_TRUE(*off);
  EXPECT_THAT(refines(*run), ::testing::Each(false));
  EXPECT_EQ(has_note(*run), 1);
  // Recorded: config.json says so, and its resume trains without it too.
  ASSERT_TRUE(WriteRunConfig(dir, run->config).ok());
  EXPECT_THAT(nlohmann::json::parse(RunConfigJson(run->config))["notes"], ::testing::Contains(kImagePosesNote));
  off = FitPosesToLog(colmap, &*run);  // a retried job: nothing more
  ASSERT_TRUE(off.ok());
  EXPECT_FALSE(*off);
  EXPECT_EQ(has_note(*run), 1);
  absl::StatusOr<ResolvedRun> resumed = ResolveRun(dir, true, CommandLineConfig{});
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_THAT(refines(*resumed), ::testing::Each(false));

  // Asked for by the user: kept on any log.
  for (const auto& g : {Given({{"pose-refinement", "true"}}), Given({{"pose-lr-scale", "2"}}),
                        Given({{"pose-refine-from", "100"}})}) {
    run = ResolveRun(dir + "/given", false, g);
    ASSERT_TRUE(run.ok()) << run.status();
    off = FitPosesToLog(colmap, &*run);
    ASSERT_TRUE(off.ok()) << off.status();
    EXPECT_FALSE(*off) << g.values[0].name;
    EXPECT_THAT(refines(*run), ::testing::Each(true)) << g.values[0].name;
  }
  // A resume of a run that refined keeps refining on any log.
  std::filesystem::create_directories(dir + "/kept");
  run = ResolveRun(dir + "/kept", false, CommandLineConfig{});
  ASSERT_TRUE(run.ok());
  ASSERT_TRUE(WriteRunConfig(dir + "/kept", run->config).ok());
  run = ResolveRun(dir + "/kept", true, CommandLineConfig{});
  ASSERT_TRUE(run.ok()) << run.status();
  ASSERT_TRUE(FitPosesToLog(colmap, &*run).ok());
  EXPECT_THAT(refines(*run), ::testing::Each(true));
  // A preset without pose refinement: nothing to do.
  CommandLineConfig preview;
  preview.preset = "preview";
  run = ResolveRun(dir + "/preview", false, preview);
  ASSERT_TRUE(run.ok());
  off = FitPosesToLog(colmap, &*run);
  ASSERT_TRUE(off.ok());
  EXPECT_FALSE(*off);
  EXPECT_EQ(has_note(*run), 0);
}

// A new run: the preset, then the settings given, which hold through the preset's schedule.
TEST(RunResolution, GivenSettingsHoldThroughThePresetsSchedule) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "new_run");
  absl::StatusOr<ResolvedRun> run = ResolveRun(dir, false, Given({{"field-lr-decay-iterations", "8000"}}));
  ASSERT_TRUE(run.ok()) << run.status();
  EXPECT_EQ(run->config.preset, "quality");
  for (const Segment& s : Segments(run->config)) EXPECT_EQ(s.settings.GetInt("field-lr-decay-iterations"), 8000);
  EXPECT_EQ(run->config.settings.GetText("field"), "s3gaussian") << "auto is pinned for resumes";
  // A short run: one segment, static (auto), the preset's prior unused rather than an error.
  run = ResolveRun(dir, false, Given({{"iterations", "40"}}));
  ASSERT_TRUE(run.ok()) << run.status();
  ASSERT_EQ(Segments(run->config).size(), 1u);
  EXPECT_EQ(run->config.settings.GetText("field"), "static");
  // Given, the same prior in a static run is a mistake.
  const absl::Status bad = ResolveRun(dir, false, Given({{"iterations", "40"}, {"field-motion-prior", "1"}})).status();
  EXPECT_TRUE(Has(std::string(bad.message()), "field-motion-prior needs a field")) << bad;
  // A scale without its stage is a mistake on the command line (a resume may end a recorded
  // stage with low-res-iterations 0 and keep its scale: cli_train_test).
  for (const auto& g : {Given({{"low-res-scale", "0.2"}}), Given({{"low-res-scale", "0.2"}, {"low-res-iterations", "0"}})}) {
    const absl::Status s = ResolveRun(dir, false, g).status();
    EXPECT_TRUE(Has(std::string(s.message()), "needs low-res-iterations")) << s;
  }
  EXPECT_EQ(ResolveRun(dir, false, [] {
              CommandLineConfig c;
              c.preset = "fast";
              return c;
            }()).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// A resume: config.json's values, and only what differs from them from the checkpoint on.
TEST(RunResolution, AResumeChangesOnlyWhatItGivesFromItsIteration) {
  absl::StatusOr<RunConfig> q = PresetConfig("quality");
  ASSERT_TRUE(q.ok());
  RunConfig config = *q;
  Settings given = config.settings;
  ASSERT_TRUE(given.SetText("densify-until", "25000", Origin::kGiven, "x").ok());  // what is in force: no change
  absl::StatusOr<std::vector<std::string>> changed = ChangeFrom(7000, given, {"densify-until"}, &config);
  ASSERT_TRUE(changed.ok());
  EXPECT_TRUE(changed->empty());
  EXPECT_EQ(RunConfigJson(config), RunConfigJson(*q));
  ASSERT_TRUE(given.SetText("densify-until", "6000", Origin::kGiven, "x").ok());
  changed = ChangeFrom(7000, given, {"densify-until"}, &config);
  ASSERT_TRUE(changed.ok());
  EXPECT_EQ(*changed, std::vector<std::string>{"densify-until"});
  std::vector<int64_t> ends;
  for (const Segment& s : Segments(config)) {
    ends.push_back(s.end);
    EXPECT_EQ(s.settings.GetInt("densify-until"), s.end <= 7000 ? 25000 : 6000) << s.end;
  }
  EXPECT_EQ(ends[2], 7000) << "the resume's iteration ends a segment";
  EXPECT_EQ(ends.back(), 14010);
  // A preset other than the run's is refused; the same one is not a change.
  const std::string dir = testing::ScratchDir("streetsim_train_config", "resume");
  ASSERT_TRUE(WriteRunConfig(dir, *q).ok());
  CommandLineConfig other;
  other.preset = "preview";
  absl::Status s = ResolveRun(dir, true, other).status();
  EXPECT_TRUE(Has(std::string(s.message()), "is a run of preset quality")) << s;
  other.preset = "quality";
  EXPECT_TRUE(ResolveRun(dir, true, other).ok());
  // A damaged config.json is not replaced by the preset's.
  std::ofstream(dir + "/config.json", std::ios::trunc) << "{\"schema";
  s = ResolveRun(dir, true, CommandLineConfig{}).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss) << s;
}

TEST(RunResolution, DirectoriesFromBeforeConfigJsonAreMigrated) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "legacy");
  std::ofstream(dir + "/checkpoint.json") << R"({"iteration": 6000, "field": "s3gaussian", "static_iterations": 5000,
    "field_lr_scale": 10, "field_lr_decay_iterations": 4500, "pose_rotation_lr": 0.0006,
    "pose_translation_lr": 0.006, "pose_refine_from": 300, "pose_refine_until": 5000,
    "position_lr_decay_iterations": 30000, "densify_until": 5000, "field_motion_prior": 0.3,
    "field_motion_prior_scans": "all"})";
  absl::StatusOr<RunConfig> c = MigrateCheckpointRecord(dir);
  ASSERT_TRUE(c.ok()) << c.status();
  const Settings& s = c->settings;
  EXPECT_EQ(s.GetText("field"), "s3gaussian");
  EXPECT_EQ(s.GetInt("field-lr-decay-iterations"), 4500);
  EXPECT_TRUE(s.GetBool("pose-refinement"));
  EXPECT_NEAR(s.GetDouble("pose-lr-scale"), 2.0, 1e-12);
  EXPECT_EQ(s.GetInt("pose-refine-until"), 5000);
  EXPECT_EQ(s.GetInt("densify-until"), 5000);
  EXPECT_DOUBLE_EQ(s.GetDouble("field-motion-prior"), 0.3);
  EXPECT_EQ(s.GetText("field-motion-prior-scans"), "all");
  std::ofstream(dir + "/checkpoint.json", std::ios::trunc) << R"({"field": "s3gaussian", "densify_until": -3})";
  EXPECT_EQ(MigrateCheckpointRecord(dir).status().code(), absl::StatusCode::kDataLoss);
}

}  // namespace
}  // namespace streetsim::train::config

namespace streetsim::train {
namespace {

TEST(StageHistory, PointsAddUpTheirTimeAndARerunReplacesThem) {
  const std::string dir = testing::ScratchDir("streetsim_train_config", "history");
  EXPECT_TRUE(absl::IsNotFound(ReadStageHistory(dir).status()));
  ASSERT_TRUE(AppendStagePoint(dir, 5000, 1200, 20.7, 0.71).ok());
  ASSERT_TRUE(AppendStagePoint(dir, 6010, 1800, 24.1, 0.80).ok());
  ASSERT_TRUE(AppendStagePoint(dir, 7510, 2000, 25.0, 0.83).ok());
  // Rolled back to 6010 and run again: the later point is replaced, its time from 6010's on.
  ASSERT_TRUE(AppendStagePoint(dir, 7510, 2100, 25.2, 0.84).ok());
  absl::StatusOr<std::vector<StagePoint>> h = ReadStageHistory(dir);
  ASSERT_TRUE(h.ok()) << h.status();
  ASSERT_EQ(h->size(), 3u);
  EXPECT_DOUBLE_EQ((*h)[2].seconds, 1200 + 1800 + 2100);
  EXPECT_DOUBLE_EQ((*h)[2].psnr, 25.2);
  const cv::Mat plot = PlotStageHistory(*h);
  EXPECT_EQ(plot.cols, 900);
  EXPECT_LT(cv::mean(plot)[0], 254.9) << "something was drawn";
  std::ofstream(dir + "/heldout_history.json", std::ios::trunc) << "{\"stages\": [1]}";
  EXPECT_EQ(ReadStageHistory(dir).status().code(), absl::StatusCode::kDataLoss);
  // A damaged history is started again, never a reason to stop the run.
  EXPECT_TRUE(AppendStagePoint(dir, 100, 10, 12, 0.4).ok());
}

}  // namespace
}  // namespace streetsim::train
