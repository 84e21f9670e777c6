// Bearer-token auth on/off, and TrainingService: jobs, idempotency, confinement, cancel,
// failure, and a restart with a job in progress.
#include <thread>

#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

class AuthJobsTest : public ServerTest {
 protected:
  v1::CreateTrainingJobRequest JobFor(const std::string& log, const std::string& name) {
    v1::CreateTrainingJobRequest req;
    req.set_log_path(log);
    req.mutable_config()->set_scene_name(name);
    return req;
  }
  absl::StatusOr<v1::Job> WaitFinal(const std::string& id) {
    return client_->WatchJob(id, [](const v1::Job&) {}, 60);
  }
};

TEST_F(AuthJobsTest, TokenRequiredWhenConfigured) {
  const std::string token_file = state_dir_ + "/token";
  std::ofstream(token_file) << "s3cret-token\n";
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.auth_token_file = token_file;
  StartServer(o, "s3cret-token");
  absl::StatusOr<v1::ServerInfo> info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_TRUE(info->auth_required());
  EXPECT_TRUE(client_->ListScenes().ok());
  for (const std::string& bad : {std::string(""), std::string("wrong"), std::string("s3cret-token2")}) {
    std::unique_ptr<client::Client> c = Connect(bad);
    EXPECT_EQ(c->GetServerInfo().status().code(), absl::StatusCode::kUnauthenticated) << bad;
    EXPECT_EQ(c->ListScenes().status().code(), absl::StatusCode::kUnauthenticated);
    EXPECT_EQ(c->CreateSession({}).status().code(), absl::StatusCode::kUnauthenticated);
    EXPECT_EQ(c->ListJobs().status().code(), absl::StatusCode::kUnauthenticated);
    v1::RenderRequest r;
    r.set_scene("street");
    EXPECT_EQ(c->Render(r).status().code(), absl::StatusCode::kUnauthenticated);
    // Health stays open for probes.
    EXPECT_TRUE(c->IsServing().ok());
  }
}

TEST_F(AuthJobsTest, NoTokenConfiguredAllowsAnyone) {
  StartServer();
  std::unique_ptr<client::Client> c = Connect("whatever");
  EXPECT_TRUE(c->GetServerInfo().ok());
  EXPECT_FALSE(c->GetServerInfo()->auth_required());
}

TEST_F(AuthJobsTest, BadServerOptionsAreRefused) {
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.auth_token_file = state_dir_ + "/missing";
  EXPECT_EQ(server::Server::Start(o).status().code(), absl::StatusCode::kInvalidArgument);
  o = TestOptions(state_dir_ + "/no_such_root", state_dir_);
  EXPECT_EQ(server::Server::Start(o).status().code(), absl::StatusCode::kInvalidArgument);
  o = TestOptions(data_root_, state_dir_);
  o.tls_cert_file = "x.pem";
  EXPECT_EQ(server::Server::Start(o).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(AuthJobsTest, JobRunsToALoadableScene) {
  StartServer();
  v1::CreateTrainingJobRequest req = JobFor("logs/fake", "trained");
  req.set_request_id("req-1");
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(req);
  ASSERT_TRUE(job.ok()) << job.status();
  EXPECT_EQ(job->scene_name(), "trained");
  // Idempotent create.
  absl::StatusOr<v1::Job> same = client_->CreateTrainingJob(req);
  ASSERT_TRUE(same.ok());
  EXPECT_EQ(same->job_id(), job->job_id());
  // The same request_id for another log or another config is an error naming it.
  v1::CreateTrainingJobRequest other = req;
  other.mutable_config()->set_seed(7);
  absl::StatusOr<v1::Job> reused = client_->CreateTrainingJob(other);
  EXPECT_EQ(reused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(reused.status().message().find("request_id 'req-1' was already used for a different training job"),
            std::string::npos) << reused.status();
  other = req;
  other.set_log_path("logs/other");
  EXPECT_EQ(client_->CreateTrainingJob(other).status().code(), absl::StatusCode::kInvalidArgument);
  int updates = 0;
  absl::StatusOr<v1::Job> done = client_->WatchJob(job->job_id(), [&](const v1::Job&) { ++updates; }, 60);
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_GE(updates, 1);
  EXPECT_DOUBLE_EQ(done->progress().fraction(), 1.0);
  EXPECT_EQ(done->progress().num_gaussians(), 4000u);
  EXPECT_FALSE(done->progress().has_metrics());  // placeholder: no trainer yet
  absl::StatusOr<v1::Scene> scene = client_->LoadScene("trained", true);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(scene->source(), "job");
  EXPECT_EQ(scene->num_gaussians(), 4000u);
  absl::StatusOr<std::vector<v1::Job>> jobs = client_->ListJobs();
  ASSERT_TRUE(jobs.ok());
  EXPECT_EQ(jobs->size(), 1u);
  // The name is now taken.
  EXPECT_EQ(client_->CreateTrainingJob(JobFor("logs/fake", "trained")).status().code(),
            absl::StatusCode::kAlreadyExists);
}

TEST_F(AuthJobsTest, JobInputsAreValidatedAndConfined) {
  StartServer();
  const std::string outside = MakeTempDir("outside");
  fs::create_directory_symlink(outside, data_root_ + "/escape");
  struct Case { std::string log, name; absl::StatusCode code; };
  const std::vector<Case> cases = {
      {"../", "a", absl::StatusCode::kInvalidArgument},
      {"logs/../../etc", "a", absl::StatusCode::kInvalidArgument},
      {"/etc", "a", absl::StatusCode::kInvalidArgument},
      {"escape", "a", absl::StatusCode::kInvalidArgument},
      {"", "a", absl::StatusCode::kInvalidArgument},
      {"logs/missing", "a", absl::StatusCode::kNotFound},
      {"logs/fake", "../x", absl::StatusCode::kInvalidArgument},
      {"logs/fake", ".hidden", absl::StatusCode::kInvalidArgument},
      {"logs/fake", "street", absl::StatusCode::kAlreadyExists},
  };
  for (const Case& c : cases) {
    EXPECT_EQ(client_->CreateTrainingJob(JobFor(c.log, c.name)).status().code(), c.code) << c.log << " " << c.name;
  }
  EXPECT_EQ(client_->GetJob("j-nope").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client_->CancelJob("j-nope").status().code(), absl::StatusCode::kNotFound);
  fs::remove_all(outside);
}

TEST_F(AuthJobsTest, FailingStageFailsTheJob) {
  StartServer();
  fs::create_directories(data_root_ + "/logs/bad");
  std::ofstream(data_root_ + "/logs/bad/fail") << "1";
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("logs/bad", "bad"));
  ASSERT_TRUE(job.ok());
  absl::StatusOr<v1::Job> done = WaitFinal(job->job_id());
  ASSERT_TRUE(done.ok());
  EXPECT_EQ(done->state(), v1::JOB_STATE_FAILED);
  EXPECT_NE(done->error().find("exited with code 3"), std::string::npos) << done->error();
}

TEST_F(AuthJobsTest, CancelStopsARunningJob) {
  StartServer();
  std::ofstream(data_root_ + "/logs/fake/sleep_s") << "30";
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("logs/fake", "slow"));
  ASSERT_TRUE(job.ok());
  for (int i = 0; i < 100 && client_->GetJob(job->job_id())->state() != v1::JOB_STATE_RUNNING; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const auto t0 = std::chrono::steady_clock::now();
  absl::StatusOr<v1::Job> cancelled = client_->CancelJob(job->job_id());
  ASSERT_TRUE(cancelled.ok());
  EXPECT_EQ(cancelled->state(), v1::JOB_STATE_CANCELLED);
  EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::seconds(5));
  EXPECT_EQ(client_->LoadScene("slow", false).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(AuthJobsTest, RestartWithAJobInProgressResumesIt) {
  std::ofstream(data_root_ + "/logs/fake/sleep_s") << "1.5";
  StartServer();
  absl::StatusOr<v1::Job> job = client_->CreateTrainingJob(JobFor("logs/fake", "resumed"));
  ASSERT_TRUE(job.ok());
  for (int i = 0; i < 200 && client_->GetJob(job->job_id())->state() != v1::JOB_STATE_RUNNING; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_EQ(client_->GetJob(job->job_id())->state(), v1::JOB_STATE_RUNNING);
  client_.reset();
  server_->Shutdown();  // as on SIGTERM: the job's record stays unfinished
  server_.reset();
  StartServer();  // same state dir
  absl::StatusOr<std::vector<v1::Job>> jobs = client_->ListJobs();
  ASSERT_TRUE(jobs.ok());
  ASSERT_EQ(jobs->size(), 1u);
  EXPECT_EQ((*jobs)[0].job_id(), job->job_id());
  absl::StatusOr<v1::Job> done = WaitFinal(job->job_id());
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->state(), v1::JOB_STATE_SUCCEEDED) << done->error();
  EXPECT_EQ(done->attempts(), 2);
  EXPECT_TRUE(client_->LoadScene("resumed", true).ok());
}

}  // namespace
}  // namespace streetsim::testing
