// The training job's "train" stage (server/job_runner.cc) with a fake trainer
// (tests/server/fake_train.sh): progress parsed from its stderr, init's scene.json kept, failure,
// cancel, resume with --resume after a restart, and no train stage when none is asked for or the
// binary has none.
#include <algorithm>
#include <map>
#include <thread>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "client/cpp/replica_set.h"
#include "scene/train/clips.h"
#include "server/job_runner.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

const std::string kFakeInit = std::string(STREETSIM_SOURCE_DIR) + "/tests/server/fake_init.sh";
const std::string kFakeTrain = std::string(STREETSIM_SOURCE_DIR) + "/tests/server/fake_train.sh";

// An init double that also writes DIR/scene.json with a rig of its own (like `streetsim init`
// writes the log's rig), so that the test can tell it survives training and publishing.
const char kInitWithManifest[] =
    R"(/bin/sh "$FAKE_INIT" "$@" && printf '%s' '{"cameras": [{"sensor_id": "cam_logged", "width": 320, "height": 96, "fx": 200, "fy": 200, "cx": 159.5, "cy": 47.5, "T_ego_from_cam": [0,0,1,0, -1,0,0,0, 0,-1,0,1.5, 0,0,0,1]}]}' > "$(dirname "$3")/scene.json")";

class TrainStageTest : public ServerTest {
 protected:
  server::ServerOptions Options() {
    server::ServerOptions o = TestOptions(data_root_, state_dir_);
    o.init_command = {"/usr/bin/env", "FAKE_INIT=" + kFakeInit, "/bin/sh", "-c", kInitWithManifest, "fake_init"};
    o.train_command = {"/bin/sh", kFakeTrain};
    return o;
  }
  v1::CreateTrainingJobRequest JobFor(const std::string& name, int iterations) {
    v1::CreateTrainingJobRequest req;
    req.set_log_path("logs/fake");
    req.mutable_config()->set_scene_name(name);
    req.mutable_config()->set_max_iterations(iterations);
    return req;
  }
  void WaitForStage(const std::string& id, const std::string& stage) {
    for (int i = 0; i < 500; ++i) {
      absl::StatusOr<v1::Job> j = client_->GetJob(id);
      if (j.ok() && j->progress().stage() == stage && j->state() == v1::JOB_STATE_RUNNING) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    FAIL() << "job " << id << " never reached stage " << stage;
  }
};

TEST(TrainProgressLine, ParsesTheTrainerFormat) {
  server::TrainProgressLine p;
  ASSERT_TRUE(server::ParseTrainProgressLine(
      "[#########.....................] 120/400  loss 0.0831  psnr 21.37 dB  153204 Gaussians  3.41 it/s  ETA 0:01:22",
      &p));
  EXPECT_EQ(p.iteration, 120);
  EXPECT_EQ(p.total, 400);
  EXPECT_DOUBLE_EQ(p.loss, 0.0831);
  EXPECT_DOUBLE_EQ(p.psnr_db, 21.37);
  EXPECT_EQ(p.gaussians, 153204u);
  EXPECT_DOUBLE_EQ(p.eta_s, 82);
  ASSERT_TRUE(server::ParseTrainProgressLine("7/9  loss 1.5  psnr nan dB  10 Gaussians", &p));
  EXPECT_EQ(p.iteration, 7);
  EXPECT_DOUBLE_EQ(p.eta_s, -1);
  EXPECT_FALSE(server::ParseTrainProgressLine("I1122 trainer.cc:1] resumed at iteration 40", &p));
  EXPECT_FALSE(server::ParseTrainProgressLine("streetsim train: 400 iterations, 1 Gaussians", &p));
  EXPECT_FALSE(server::ParseTrainProgressLine("3/0  loss 1  psnr 2 dB  5 Gaussians", &p));
}

TEST_F(TrainStageTest, TrainStageReportsProgressAndKeepsTheInitManifest) {
  std::ofstream(data_root_ + "/logs/fake/train_sleep_s") << "0.15";
  ASSERT_TRUE(cv::imwrite(data_root_ + "/logs/fake/preview.png", cv::Mat(100, 800, CV_8UC3, cv::Scalar(10, 200, 30))));
  std::ofstream(data_root_ + "/logs/fake/heldout.json") << R"({"views": 2, "frames": [
      {"frame": 3, "psnr": 21.0, "ssim": 0.7, "psnr_dynamic": 18.5},
      {"frame": 7, "psnr": 23.0, "ssim": 0.8, "psnr_dynamic": null}],
    "mean": {"psnr": 22.0, "ssim": 0.75, "psnr_dynamic": 18.5}})";
  StartServer(Options());
  v1::CreateTrainingJobRequest req = JobFor("trained", 8);
  req.mutable_config()->set_seed(7);
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(req);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->progress().num_stages(), 3);
  std::vector<v1::Job> updates;
  absl::StatusOr<v1::Job> done =
      client_->WatchJob(job->job_id(), [&](const v1::Job& j) { updates.push_back(j); }, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  const v1::JobProgress& p = done->progress();
  EXPECT_EQ(p.stage(), "done");
  EXPECT_EQ(p.stage_index(), 3);
  EXPECT_EQ(p.num_stages(), 3);
  EXPECT_DOUBLE_EQ(p.fraction(), 1.0);
  EXPECT_TRUE(p.has_metrics());
  EXPECT_EQ(p.iteration(), 8);
  EXPECT_EQ(p.max_iterations(), 8);
  EXPECT_DOUBLE_EQ(p.loss(), 0.0992);
  EXPECT_DOUBLE_EQ(p.psnr_db(), 28.5);
  EXPECT_EQ(p.num_gaussians(), 4000u);
  // The trainer's held-out metrics (its DIR/heldout.json).
  EXPECT_EQ(done->heldout().views(), 2);
  EXPECT_DOUBLE_EQ(done->heldout().psnr_db(), 22.0);
  EXPECT_DOUBLE_EQ(done->heldout().ssim(), 0.75);
  EXPECT_DOUBLE_EQ(done->heldout().psnr_dynamic_db(), 18.5);
  // The trainer's held-out preview, scaled down for the record.
  const std::string& png = p.preview_png();
  const cv::Mat preview = cv::imdecode(std::vector<uchar>(png.begin(), png.end()), cv::IMREAD_COLOR);
  ASSERT_FALSE(preview.empty());
  EXPECT_EQ(preview.cols, 384);
  EXPECT_EQ(preview.rows, 48);
  EXPECT_EQ(preview.at<cv::Vec3b>(10, 10), cv::Vec3b(10, 200, 30));
  // Seen while training: stage "train" with metrics part-way, fractions never going back.
  bool saw_partial_train = false;
  double last_fraction = 0;
  for (const v1::Job& u : updates) {
    EXPECT_GE(u.progress().fraction(), last_fraction);
    last_fraction = u.progress().fraction();
    if (u.progress().stage() == "train" && u.progress().has_metrics() && u.progress().iteration() < 8) {
      saw_partial_train = true;
      EXPECT_EQ(u.progress().stage_index(), 1);
      EXPECT_GT(u.progress().fraction(), 0.0);
      EXPECT_LT(u.progress().fraction(), 1.0);
      EXPECT_GE(u.progress().eta_s(), 0);
    }
  }
  EXPECT_TRUE(saw_partial_train) << updates.size() << " updates";
  // The trainer ran on the job's work dir, which was published with init's scene.json.
  const std::string published = state_dir_ + "/scenes/trained";
  std::ifstream trained(published + "/trained");
  std::string trained_line;
  std::getline(trained, trained_line);
  EXPECT_EQ(trained_line, "iterations 8 seed 7");
  EXPECT_FALSE(fs::exists(published + "/resumed"));
  absl::StatusOr<v1::Scene> scene = client_->LoadScene("trained", true);
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->rig().cameras_size(), 1);
  EXPECT_EQ(scene->rig().cameras(0).sensor_id(), "cam_logged");
  EXPECT_EQ(scene->num_gaussians(), 4000u);
}

TEST_F(TrainStageTest, AFinishedJobShowsItsLastIterationNotItsLastProgressLine) {
  // The trainer's last progress line was its first iteration; the finished job says 6 of 6.
  std::ofstream(data_root_ + "/logs/fake/train_progress_once") << "";
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("quiet", 6));
  ASSERT_TRUE(job.ok()) << job.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->progress().iteration(), 6);
  EXPECT_EQ(done->progress().max_iterations(), 6);
}

TEST_F(TrainStageTest, AClipSetReportsItsClipsTogether) {
  // What `streetsim train --clip-frames` leaves: DIR/clips.json and a scene per clip, each with
  // its held-out metrics; the job reports their union and the Gaussians of every clip.
  const std::string clips = data_root_ + "/logs/fake/clips";
  for (const char* clip : {"clip_000", "clip_001"}) fs::create_directories(clips + "/" + clip);
  train::ClipSet set;
  set.clip_frames = 4;
  set.num_frames = 12;
  set.clips = {{{0, 4}, 0, 300000, "clip_000", true}, {{4, 12}, 400000, 1100000, "clip_001", true}};
  ASSERT_TRUE(train::WriteClipSet(set, clips).ok());
  std::ofstream(clips + "/clip_000/heldout.json") << R"({"frames": [
      {"frame": 3, "psnr": 20.0, "ssim": 0.70, "psnr_dynamic": 18.0}],
    "mean": {"psnr": 20.0, "ssim": 0.70, "psnr_dynamic": 18.0}})";
  std::ofstream(clips + "/clip_001/heldout.json") << R"({"frames": [
      {"frame": 7, "psnr": 24.0, "ssim": 0.80, "psnr_dynamic": null},
      {"frame": 11, "psnr": 26.0, "ssim": 0.90, "psnr_dynamic": 22.0}],
    "mean": {"psnr": 25.0, "ssim": 0.85, "psnr_dynamic": 22.0}})";
  std::ofstream(clips + "/clip_000/scene.ply") << "ply\nformat binary_little_endian 1.0\nelement vertex 1200\nend_header\n";
  std::ofstream(clips + "/clip_001/scene.ply") << "ply\nformat binary_little_endian 1.0\nelement vertex 800\nend_header\n";
  StartServer(Options());
  v1::CreateTrainingJobRequest req = JobFor("clip_set", 4);
  req.mutable_config()->set_clip_frames(4);
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(req);
  ASSERT_TRUE(job.ok()) << job.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->progress().num_gaussians(), 2000u);  // not init's scene.ply beside clips.json
  EXPECT_EQ(done->heldout().views(), 3);
  EXPECT_NEAR(done->heldout().psnr_db(), (20.0 + 24.0 + 26.0) / 3, 1e-9);
  EXPECT_NEAR(done->heldout().ssim(), (0.70 + 0.80 + 0.90) / 3, 1e-9);
  EXPECT_NEAR(done->heldout().psnr_dynamic_db(), (18.0 + 22.0) / 2, 1e-9);  // over the views that have any
}

TEST_F(TrainStageTest, AJobContinuesAnotherJobsScene) {
  StartServer(Options());
  v1::CreateTrainingJobRequest first_req = JobFor("first", 8);
  first_req.mutable_config()->set_field("s3gaussian");
  first_req.mutable_config()->set_static_iterations(4);
  absl::StatusOr<v1::Job> first = client_->CreateTrainingJob(first_req);
  ASSERT_TRUE(first.ok()) << first.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(first->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok() && done->state() == v1::JOB_STATE_SUCCEEDED) << done.status() << done->error();

  // Refused before a job exists: fewer iterations than the scene has, an unknown scene, another
  // log, a name that is a path.
  v1::CreateTrainingJobRequest req = JobFor("longer", 8);
  req.mutable_config()->set_continue_from_scene("first");
  EXPECT_EQ(client_->CreateTrainingJob(req).status().code(), absl::StatusCode::kInvalidArgument);
  req.mutable_config()->set_max_iterations(12);
  req.mutable_config()->set_continue_from_scene("nope");
  EXPECT_EQ(client_->CreateTrainingJob(req).status().code(), absl::StatusCode::kNotFound);
  req.mutable_config()->set_continue_from_scene("../scenes/first");
  EXPECT_EQ(client_->CreateTrainingJob(req).status().code(), absl::StatusCode::kInvalidArgument);
  fs::create_directories(data_root_ + "/logs/other");
  v1::CreateTrainingJobRequest other_log = req;
  other_log.set_log_path("logs/other");
  other_log.mutable_config()->set_continue_from_scene("first");
  absl::StatusOr<v1::Job> refused = client_->CreateTrainingJob(other_log);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("was trained from log_path 'logs/fake'"), std::string::npos)
      << refused.status();

  // Continued: the trainer resumes the copy at the scene's checkpoint (8) with the new options and
  // trains to 12; the source scene is untouched.
  req.mutable_config()->set_continue_from_scene("first");
  req.mutable_config()->set_field_lr_decay_iterations(600);
  absl::StatusOr<v1::Job> longer = client_->CreateTrainingJob(req);
  ASSERT_TRUE(longer.ok()) << longer.status();
  done = client_->WatchJob(longer->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->progress().iteration(), 12);
  std::ifstream resumed(state_dir_ + "/scenes/longer/resumed");
  int from = -1;
  resumed >> from;
  EXPECT_EQ(from, 8);
  std::ifstream flags(state_dir_ + "/scenes/longer/flags");
  std::vector<std::string> runs;
  for (std::string line; std::getline(flags, line);) runs.push_back(line);
  EXPECT_EQ(runs, (std::vector<std::string>{"--set field=s3gaussian --set static-iterations=4",  // the source's run
                                            "--set field-lr-decay-iterations=600"}));
  std::ifstream source_trained(state_dir_ + "/scenes/first/trained");
  std::string line;
  std::getline(source_trained, line);
  EXPECT_EQ(line, "iterations 8");
  EXPECT_FALSE(fs::exists(state_dir_ + "/scenes/first/resumed"));
  // A static scene has no field rates to set.
  v1::CreateTrainingJobRequest static_req = JobFor("static_src", 4);
  static_req.mutable_config()->set_field("static");
  absl::StatusOr<v1::Job> static_job = client_->CreateTrainingJob(static_req);
  ASSERT_TRUE(static_job.ok()) << static_job.status();
  ASSERT_TRUE(client_->WatchJob(static_job->job_id(), [](const v1::Job&) {}, 60).ok());
  v1::CreateTrainingJobRequest anneal_static = JobFor("static_more", 8);
  anneal_static.mutable_config()->set_continue_from_scene("static_src");
  anneal_static.mutable_config()->set_field_lr_decay_iterations(600);
  absl::StatusOr<v1::Job> anneal = client_->CreateTrainingJob(anneal_static);
  EXPECT_EQ(anneal.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(anneal.status().message().find("static scene"), std::string::npos) << anneal.status();
  // Nor a motion prior.
  v1::CreateTrainingJobRequest prior_static = JobFor("static_prior", 8);
  prior_static.mutable_config()->set_continue_from_scene("static_src");
  prior_static.mutable_config()->set_field_motion_prior(0.3);
  absl::StatusOr<v1::Job> prior = client_->CreateTrainingJob(prior_static);
  EXPECT_EQ(prior.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(prior.status().message().find("field_motion_prior and"), std::string::npos) << prior.status();
  prior_static.mutable_config()->clear_field_motion_prior();
  prior_static.mutable_config()->set_field_motion_prior_scans("all");
  prior = client_->CreateTrainingJob(prior_static);
  EXPECT_EQ(prior.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(prior.status().message().find("static scene"), std::string::npos) << prior.status();
  absl::StatusOr<v1::Scene> scene = client_->LoadScene("longer", true);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->rig().cameras(0).sensor_id(), "cam_logged");  // the source's manifest came along
}

TEST_F(TrainStageTest, NoIterationsMeansNoTrainStage) {
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("init_only", 0));
  ASSERT_TRUE(job.ok()) << job.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->progress().num_stages(), 2);
  EXPECT_FALSE(done->progress().has_metrics());
  EXPECT_EQ(done->heldout().views(), 0);
  EXPECT_FALSE(fs::exists(state_dir_ + "/scenes/init_only/trained"));
}

TEST_F(TrainStageTest, WithoutATrainerNothingIsContinued) {
  server::ServerOptions o = Options();
  o.train_command.clear();
  StartServer(o);
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("init_only", 0));
  ASSERT_TRUE(job.ok()) << job.status();
  ASSERT_TRUE(client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60).ok());
  v1::CreateTrainingJobRequest req = JobFor("more", 50);
  req.mutable_config()->set_continue_from_scene("init_only");
  EXPECT_EQ(client_->CreateTrainingJob(req).status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST_F(TrainStageTest, WithoutATrainerOnlyInitRuns) {
  // Default train command: `streetsim` next to this test binary, which has none.
  server::ServerOptions o = Options();
  o.train_command.clear();
  StartServer(o);
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("no_trainer", 50));
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->progress().num_stages(), 2);
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->progress().num_stages(), 2);
  EXPECT_FALSE(done->progress().has_metrics());
  EXPECT_TRUE(client_->LoadScene("no_trainer", true).ok());
}

TEST_F(TrainStageTest, FailingTrainerFailsTheJob) {
  std::ofstream(data_root_ + "/logs/fake/train_fail") << "1";
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("bad", 5));
  ASSERT_TRUE(job.ok());
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok());
  EXPECT_EQ(done->state(), v1::JOB_STATE_FAILED);
  EXPECT_EQ(done->progress().stage(), "train");
  // The trainer's own last line says why, so a remote user need not read the server's files.
  EXPECT_NE(done->error().find("train stage exited with code 5: failing as asked"), std::string::npos)
      << done->error();
  EXPECT_NE(done->error().find("train.log"), std::string::npos) << done->error();
  EXPECT_EQ(client_->LoadScene("bad", false).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(TrainStageTest, CancelStopsTheTrainer) {
  std::ofstream(data_root_ + "/logs/fake/train_sleep_s") << "0.5";
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("slow", 1000));
  ASSERT_TRUE(job.ok());
  WaitForStage(job->job_id(), "train");
  const auto t0 = std::chrono::steady_clock::now();
  absl::StatusOr<v1::Job> cancelled = client_->CancelJob(job->job_id());
  ASSERT_TRUE(cancelled.ok());
  EXPECT_EQ(cancelled->state(), v1::JOB_STATE_CANCELLED);
  EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::seconds(5));
  EXPECT_EQ(client_->LoadScene("slow", false).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(TrainStageTest, RestartResumesTheTrainerFromItsCheckpoint) {
  std::ofstream(data_root_ + "/logs/fake/train_sleep_s") << "0.1";
  StartServer(Options());
  // 40 iterations of 0.1 s: room for the stop to land before the trainer finishes on a loaded
  // machine (the test's threads may wait a second or more for a core).
  // With the config's training options, which the resumed run must get again.
  v1::CreateTrainingJobRequest req = JobFor("resumed", 40);
  req.mutable_config()->set_static_iterations(20);
  req.mutable_config()->set_low_res_scale(0.25);
  req.mutable_config()->set_low_res_iterations(10);
  req.mutable_config()->set_holdout_every(0);
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(req);
  ASSERT_TRUE(job.ok()) << job.status();
  // Wait until the trainer has checkpointed a few iterations.
  for (int i = 0; i < 1500; ++i) {
    absl::StatusOr<v1::Job> j = client_->GetJob(job->job_id());
    if (j.ok() && j->progress().stage() == "train" && j->progress().iteration() >= 3) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  absl::StatusOr<v1::Job> mid = client_->GetJob(job->job_id());
  ASSERT_TRUE(mid.ok());
  ASSERT_EQ(mid->progress().stage(), "train");
  ASSERT_GE(mid->progress().iteration(), 3);
  ASSERT_LT(mid->progress().iteration(), 40);
  client_.reset();
  server_->Shutdown();  // as on SIGTERM: the trainer is stopped, the record stays unfinished
  server_.reset();
  StartServer(Options());
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->attempts(), 2);
  EXPECT_EQ(done->progress().iteration(), 40);
  // The second run got --resume and continued from the checkpoint (not from 0); init did not
  // run again (the manifest it wrote is still the one published).
  std::ifstream resumed(state_dir_ + "/scenes/resumed/resumed");
  int from = -1;
  resumed >> from;
  EXPECT_GE(from, 3);
  EXPECT_LT(from, 40);
  absl::StatusOr<v1::Scene> scene = client_->LoadScene("resumed", true);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->rig().cameras(0).sensor_id(), "cam_logged");
  std::ifstream flags(state_dir_ + "/scenes/resumed/flags");
  std::vector<std::string> runs;
  for (std::string line; std::getline(flags, line);) runs.push_back(line);
  const std::string want =
      "--set static-iterations=20 --set low-res-scale=0.25 --set low-res-iterations=10 --set holdout-every=0";
  EXPECT_EQ(runs, (std::vector<std::string>{want, want}));
}

TEST_F(TrainStageTest, ServerInfoSaysJobsTrain) {
  StartServer(Options());
  absl::StatusOr<v1::ServerInfo> info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  const std::vector<std::string> caps(info->capabilities().begin(), info->capabilities().end());
  EXPECT_NE(std::find(caps.begin(), caps.end(), "training:train"), caps.end());
  EXPECT_EQ(std::find(caps.begin(), caps.end(), "training:init-only"), caps.end());
}

TEST_F(TrainStageTest, AKilledTrainerGoesOnFromItsCheckpoint) {
  // The fake trainer kills itself with SIGKILL after its 5th checkpoint, as the OOM killer or an
  // operator would: the job resumes it within the same attempt and loses nothing checkpointed.
  std::ofstream(data_root_ + "/logs/fake/train_kill_at") << "5";
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("killed", 12));
  ASSERT_TRUE(job.ok()) << job.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  ASSERT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->attempts(), 1);
  EXPECT_EQ(done->progress().iteration(), 12);
  std::ifstream resumed(state_dir_ + "/scenes/killed/resumed");
  int from = -1;
  resumed >> from;
  EXPECT_EQ(from, 5);
}

TEST_F(TrainStageTest, ATrainerKilledOverAndOverFailsTheJob) {
  // Killed on every run (after its first iteration): the job gives up after a bounded number of
  // restarts, with the exit code in its error.
  std::ofstream(data_root_ + "/logs/fake/train_kill_at") << "1";
  std::ofstream(data_root_ + "/logs/fake/train_kill_every_run") << "1";
  StartServer(Options());
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("doomed", 50));
  ASSERT_TRUE(job.ok()) << job.status();
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [](const v1::Job&) {}, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->state(), v1::JOB_STATE_FAILED);
  EXPECT_NE(done->error().find("exited with code 137"), std::string::npos) << done->error();
  std::ifstream flags(state_dir_ + "/jobs/" + job->job_id() + "/work/flags");
  int runs = 0;
  for (std::string line; std::getline(flags, line);) ++runs;
  EXPECT_EQ(runs, 4);  // the first run and three restarts
}

TEST_F(TrainStageTest, BadTrainingOptionsAreRefusedAtCreation) {
  StartServer(Options());
  v1::CreateTrainingJobRequest req = JobFor("bad_options", 100);
  req.mutable_config()->set_low_res_scale(0.25);  // without low_res_iterations
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(req);
  EXPECT_EQ(job.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(job.status().message().find("low-res-scale needs low-res-iterations > 0"), std::string::npos)
      << job.status();
  req = JobFor("bad_options", 100);
  (*req.mutable_config()->mutable_settings())["densify-untill"] = "5";
  job = client_->CreateTrainingJob(req);
  EXPECT_EQ(job.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(job.status().message().find("unknown setting 'densify-untill'"), std::string::npos) << job.status();
  req = JobFor("bad_options", 0);
  req.mutable_config()->set_field("s3gaussian");
  EXPECT_EQ(client_->CreateTrainingJob(req).status().code(), absl::StatusCode::kInvalidArgument);
  // Nothing was queued.
  absl::StatusOr<std::vector<v1::Job>> jobs = client_->ListJobs();
  ASSERT_TRUE(jobs.ok());
  EXPECT_TRUE(jobs->empty());
}

}  // namespace
}  // namespace streetsim::testing

namespace streetsim::testing {
namespace {

// Replicas sharing one state dir (server/replica.h): ids name their replica, each replica runs
// only its own jobs, another replica reports them and sends cancels to their owner.
class ReplicaTest : public TrainStageTest {
 protected:
  server::ServerOptions Named(const std::string& name) {
    server::ServerOptions o = Options();
    o.replica = name;
    return o;
  }
};

TEST_F(ReplicaTest, IdsNameTheReplicaAndJobsStayWithTheirOwner) {
  std::ofstream(data_root_ + "/logs/fake/train_sleep_s") << "0.1";
  StartServer(Named("r0"));
  absl::StatusOr<std::unique_ptr<server::Server>> other = server::Server::Start(Named("r1"));
  ASSERT_TRUE(other.ok()) << other.status();
  client::ClientOptions co;
  co.target = (*other)->address();
  absl::StatusOr<std::unique_ptr<client::Client>> r1 = client::Client::Connect(co);
  ASSERT_TRUE(r1.ok());

  v1::CreateSessionRequest sreq;
  sreq.set_scene("timed");
  absl::StatusOr<v1::Session> session = client_->CreateSession(sreq);
  ASSERT_TRUE(session.ok()) << session.status();
  EXPECT_EQ(session->session_id().rfind("r0.s-", 0), 0u) << session->session_id();
  v1::StepRequest step;
  step.set_session_id(session->session_id());
  step.set_step_index(0);
  absl::StatusOr<v1::StepResponse> elsewhere = (*r1)->Step(step);
  ASSERT_FALSE(elsewhere.ok());
  EXPECT_EQ(elsewhere.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(elsewhere.status().message().find("belongs to replica 'r0'"), std::string::npos)
      << elsewhere.status();

  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("shared", 200));
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->job_id().rfind("r0.j-", 0), 0u) << job->job_id();
  WaitForStage(job->job_id(), "train");
  // r1 reports r0's job from the shared records, lists it, and sends its cancel to r0.
  absl::StatusOr<v1::Job> seen = (*r1)->GetJob(job->job_id());
  ASSERT_TRUE(seen.ok()) << seen.status();
  EXPECT_EQ(seen->config().scene_name(), "shared");
  // Another replica's records are read from disk by id: an id that is not a job's name reads nothing.
  for (const std::string& bad : std::vector<std::string>{"r0/../../jobs", "../r0.j-1", "r0.j-1/../../x", ".hidden",
                                                         std::string(300, 'r')}) {
    absl::StatusOr<v1::Job> none = (*r1)->GetJob(bad);
    ASSERT_FALSE(none.ok()) << bad;
    EXPECT_EQ(none.status().code(), absl::StatusCode::kNotFound) << none.status();
  }
  absl::StatusOr<v1::Job> refused = (*r1)->CancelJob(job->job_id());
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition) << refused.status();
  // A restart of r1 does not adopt r0's running job (only r0 runs and writes it).
  r1->reset();
  other->reset();
  other = server::Server::Start(Named("r1"));
  ASSERT_TRUE(other.ok()) << other.status();
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  std::ifstream flags(state_dir_ + "/jobs/" + job->job_id() + "/work/flags");
  int trainer_runs = 0;
  for (std::string line; std::getline(flags, line);) ++trainer_runs;
  EXPECT_EQ(trainer_runs, 1);  // r0's trainer only (each run of the fake trainer adds a line)
  absl::StatusOr<v1::Job> cancelled = client_->CancelJob(job->job_id());
  ASSERT_TRUE(cancelled.ok()) << cancelled.status();
  EXPECT_EQ(cancelled->state(), v1::JOB_STATE_CANCELLED);
}

TEST_F(ReplicaTest, TheCppReplicaSetRoutesSessionsAndFailsOver) {
  StartServer(Named("r0"));
  absl::StatusOr<std::unique_ptr<server::Server>> r1 = server::Server::Start(Named("r1"));
  ASSERT_TRUE(r1.ok()) << r1.status();
  client::ClientOptions co;
  co.timeout_s = 30;
  absl::StatusOr<std::unique_ptr<client::ReplicaSet>> set =
      client::ReplicaSet::Connect({{"r0", server_->address()}, {"r1", (*r1)->address()}}, co);
  ASSERT_TRUE(set.ok()) << set.status();
  v1::CreateSessionRequest sreq;
  sreq.set_scene("timed");
  std::vector<std::string> owners;
  for (int i = 0; i < 4; ++i) {
    absl::StatusOr<v1::Session> s = (*set)->CreateSession(sreq);
    ASSERT_TRUE(s.ok()) << s.status();
    owners.emplace_back(client::ReplicaOfId(s->session_id()));
    v1::StepRequest step;
    step.set_session_id(s->session_id());
    step.set_step_index(0);
    absl::StatusOr<v1::StepResponse> r = (*set)->Step(step);  // reaches the session's own replica
    ASSERT_TRUE(r.ok()) << r.status();
  }
  std::sort(owners.begin(), owners.end());
  EXPECT_EQ(owners, (std::vector<std::string>{"r0", "r0", "r1", "r1"}));
  // r1 goes away: stateless renders fail over to r0, every time.
  r1->reset();
  v1::RenderRequest render;
  render.set_scene("timed");
  render.set_time_us(100000);
  for (int i = 0; i < 4; ++i) {
    absl::StatusOr<v1::RenderResponse> r = (*set)->Render(render);
    ASSERT_TRUE(r.ok()) << r.status();
  }
  EXPECT_FALSE(client::ReplicaSet::Connect(std::map<std::string, std::string>{}, co).ok());
  EXPECT_FALSE(client::ReplicaSet::Connect({"a"}, "no-placeholder:1", co).ok());
}

TEST_F(ReplicaTest, ABadReplicaNameIsRefused) {
  for (const char* bad : {"R0", "-r", "r.0", "a/b"}) {
    absl::StatusOr<std::unique_ptr<server::Server>> s = server::Server::Start(Named(bad));
    ASSERT_FALSE(s.ok()) << bad;
    EXPECT_EQ(s.status().code(), absl::StatusCode::kInvalidArgument) << s.status();
  }
}

}  // namespace
}  // namespace streetsim::testing
