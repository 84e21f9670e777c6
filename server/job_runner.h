// Runs training jobs: a pipeline of stages with progress, cancel, persistence and resume.
//
// PLACEHOLDER PIPELINE: until the trainer lands, the pipeline is
//   1. "init": `<init_command> LOG_ABS_PATH --out WORK/scene.ply` as a child process (default
//      init_command: the `streetsim init` subcommand next to this binary), its output in
//      <job dir>/init.log, its exit code checked;
//   2. "publish": WORK/scene.json written if the stage did not write one, WORK renamed to
//      <state_dir>/scenes/<scene_name> (then loadable by name).
// The "train" stage (scene/train) will slot in between. Unfinished jobs (QUEUED or RUNNING in
// their record) are re-queued at start; a stage that had finished is not run again.
#pragma once

#include <sys/types.h>

#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "server/job_store.h"
#include "server/service_deps.h"
#include "streetsim/v1/training.pb.h"

namespace streetsim::server {

struct JobRunnerOptions {
  std::string data_root;
  std::vector<std::string> init_command;  // argv prefix; empty: {<exe dir>/streetsim, "init"}
};

class JobRunner {
 public:
  JobRunner(JobStore* store, ServiceDeps* deps, JobRunnerOptions options);
  ~JobRunner();

  // Re-queues unfinished jobs and starts the workers.
  void Start();
  // Stops the workers: running children are terminated, their records stay RUNNING (resumed at
  // the next start).
  void Stop();

  absl::StatusOr<v1::Job> Create(const v1::CreateTrainingJobRequest& req);
  absl::StatusOr<v1::Job> Cancel(const std::string& id);
  int running();
  JobStore* store() { return store_; }

 private:
  void WorkerLoop();
  void RunJob(const std::string& id);
  // Runs argv as a child; returns its exit code, or CANCELLED / UNAVAILABLE (stopping).
  absl::StatusOr<int> RunChild(const std::string& id, const std::vector<std::string>& argv,
                               const std::string& log_path, v1::Job* job);
  bool CancelRequested(const std::string& id);

  JobStore* store_;
  ServiceDeps* deps_;
  JobRunnerOptions options_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<std::string> queue_;
  std::set<std::string> cancel_requested_;
  std::set<std::string> running_;
  std::vector<std::thread> workers_;
  bool stopping_ = false;
};

bool IsFinal(v1::JobState state);

}  // namespace streetsim::server
