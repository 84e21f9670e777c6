// Low resolution first (scene/train/resolution_schedule.h): which stages run, at what scale, with
// what resume / outputs, from a fresh start and from checkpoints on either side of the switch.
// The stages here are recorded, not trained (cli_train_test.cc trains one through the switch).
#include "scene/train/resolution_schedule.h"

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"

namespace streetsim::train {
namespace {

struct StageCall {
  double scale;
  int iterations;
  bool resume, write_outputs;
};

// A header-only checkpoint: what PeekCheckpointIteration reads.
void WriteCheckpointHeader(const std::string& dir, int64_t iteration) {
  std::ofstream f(dir + "/checkpoint.bin", std::ios::binary | std::ios::trunc);
  f.write("SSTRN001", 8);
  f.write(reinterpret_cast<const char*>(&iteration), sizeof(iteration));
}

class ResolutionStages : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = streetsim::testing::ScratchDir("resolution_schedule", ::testing::UnitTest::GetInstance()->current_test_info()->name());
    opt_.iterations = 100;
    opt_.resolution_scale = 1.0;
    opt_.low_res = LowResStage{0.25, 40};
  }
  // Runs the schedule with a stage that records its call, reports progress at its first and last
  // iteration and "trains" to `stop_at(stage)` iterations.
  absl::StatusOr<TrainResult> Run(const std::function<int(const TrainOptions&)>& stop_at = nullptr,
                                  absl::Status fail_first = absl::OkStatus()) {
    return TrainInResolutionStages(
        opt_, dir_, [&](const Progress& p) { progress_.push_back(p); },
        [&](const TrainOptions& stage, const std::function<void(const Progress&)>& progress) -> absl::StatusOr<TrainResult> {
          calls_.push_back({stage.resolution_scale, stage.iterations, stage.resume, stage.write_outputs});
          EXPECT_EQ(stage.low_res.has_value(), true);  // both stages carry it (train_meta.json records it)
          if (calls_.size() == 1 && !fail_first.ok()) return fail_first;
          const int end = stop_at ? stop_at(stage) : stage.iterations;
          for (int it : {1, end}) {
            Progress p;
            p.iteration = it;
            p.total = stage.iterations;
            progress(p);
          }
          TrainResult r;
          r.iterations = end;
          r.seconds = stage.resolution_scale < 1 ? 1.5 : 2.0;
          r.seconds_to_psnr24 = stage.resolution_scale < 1 ? 0.5 : 1.0;
          return r;
        });
  }
  std::string dir_;
  TrainOptions opt_;
  std::vector<StageCall> calls_;
  std::vector<Progress> progress_;
};

TEST_F(ResolutionStages, AFreshRunTrainsLowThenResumesAtItsOwnScale) {
  absl::StatusOr<TrainResult> r = Run();
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->iterations, 100);
  EXPECT_DOUBLE_EQ(r->seconds, 3.5);  // both stages' time
  EXPECT_DOUBLE_EQ(r->seconds_to_psnr24, 2.5);  // reached at the run's resolution, 1.0 s into it
  ASSERT_EQ(calls_.size(), 2u);
  EXPECT_DOUBLE_EQ(calls_[0].scale, 0.25);
  EXPECT_EQ(calls_[0].iterations, 40);
  EXPECT_FALSE(calls_[0].resume);
  EXPECT_FALSE(calls_[0].write_outputs);  // outputs come from the run's resolution only
  EXPECT_DOUBLE_EQ(calls_[1].scale, 1.0);
  EXPECT_EQ(calls_[1].iterations, 100);
  EXPECT_TRUE(calls_[1].resume);  // from the low-resolution stage's checkpoint
  EXPECT_TRUE(calls_[1].write_outputs);
  // Progress counts against the whole run and says which stage it is in.
  ASSERT_EQ(progress_.size(), 4u);
  EXPECT_EQ(progress_[1].iteration, 40);
  EXPECT_EQ(progress_[1].total, 100);
  EXPECT_DOUBLE_EQ(progress_[1].low_res_scale, 0.25);
  EXPECT_EQ(progress_[3].total, 100);
  EXPECT_DOUBLE_EQ(progress_[3].low_res_scale, 0.0);
}

TEST_F(ResolutionStages, ResumePastTheSwitchSkipsTheLowStage) {
  opt_.resume = true;
  WriteCheckpointHeader(dir_, 40);  // the low stage's last iteration: done
  ASSERT_TRUE(Run().ok());
  ASSERT_EQ(calls_.size(), 1u);
  EXPECT_DOUBLE_EQ(calls_[0].scale, 1.0);
  EXPECT_TRUE(calls_[0].resume);
}

TEST_F(ResolutionStages, ResumeInsideTheLowStageFinishesItFirst) {
  opt_.resume = true;
  WriteCheckpointHeader(dir_, 39);
  ASSERT_TRUE(Run().ok());
  ASSERT_EQ(calls_.size(), 2u);
  EXPECT_DOUBLE_EQ(calls_[0].scale, 0.25);
  EXPECT_TRUE(calls_[0].resume);
  EXPECT_DOUBLE_EQ(calls_[1].scale, 1.0);
}

TEST_F(ResolutionStages, WithoutResumeAnOldCheckpointIsNotConsulted) {
  WriteCheckpointHeader(dir_, 90);
  ASSERT_TRUE(Run().ok());
  ASSERT_EQ(calls_.size(), 2u);
  EXPECT_FALSE(calls_[0].resume);
}

TEST_F(ResolutionStages, AStageThatStopsEarlyEndsTheRun) {
  // Stopped inside the low stage (a signal, or stop_after): no resolution switch afterwards.
  absl::StatusOr<TrainResult> r = Run([](const TrainOptions&) { return 17; });
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->iterations, 17);
  EXPECT_EQ(calls_.size(), 1u);
  // stop_after on the switch itself stops there too.
  calls_.clear();
  opt_.stop_after = 40;
  r = Run();
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->iterations, 40);
  EXPECT_EQ(calls_.size(), 1u);
  // A failure (or a cancel) in the low stage is the run's.
  calls_.clear();
  opt_.stop_after = 0;
  r = Run(nullptr, absl::CancelledError("stopped at iteration 12"));
  EXPECT_TRUE(absl::IsCancelled(r.status())) << r.status();
  EXPECT_EQ(calls_.size(), 1u);
}

TEST_F(ResolutionStages, BadStagesAndCheckpointsAreRefusedBeforeTraining) {
  for (const LowResStage& bad : {LowResStage{1.0, 40}, LowResStage{1.5, 40}, LowResStage{0.0, 40},
                                 LowResStage{-0.25, 40}, LowResStage{0.25, 0}, LowResStage{0.25, 100},
                                 LowResStage{0.25, 1000}}) {
    opt_.low_res = bad;
    absl::StatusOr<TrainResult> r = Run();
    EXPECT_TRUE(absl::IsInvalidArgument(r.status())) << bad.resolution_scale << " " << bad.iterations;
    EXPECT_TRUE(absl::IsInvalidArgument(CheckLowResStage(opt_)));
  }
  EXPECT_TRUE(calls_.empty());
  opt_.low_res = LowResStage{0.25, 40};
  EXPECT_TRUE(CheckLowResStage(opt_).ok());
  opt_.resume = true;
  std::ofstream(dir_ + "/checkpoint.bin") << "not a checkpoint";
  absl::StatusOr<TrainResult> r = Run();
  EXPECT_TRUE(absl::IsDataLoss(r.status())) << r.status();
  EXPECT_TRUE(calls_.empty());
}

TEST_F(ResolutionStages, WithoutALowStageTheRunIsOneStageAsGiven) {
  opt_.low_res.reset();
  opt_.resolution_scale = 0.5;
  TrainOptions seen;
  ASSERT_TRUE(TrainInResolutionStages(opt_, dir_, nullptr,
                                      [&](const TrainOptions& stage, const std::function<void(const Progress&)>&)
                                          -> absl::StatusOr<TrainResult> {
                                        seen = stage;
                                        return TrainResult{};
                                      })
                  .ok());
  EXPECT_DOUBLE_EQ(seen.resolution_scale, 0.5);
  EXPECT_EQ(seen.iterations, 100);
  EXPECT_FALSE(seen.resume);
  EXPECT_TRUE(seen.write_outputs);
}

}  // namespace
}  // namespace streetsim::train
