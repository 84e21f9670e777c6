// Runs training jobs: a pipeline of stages with progress, cancel, persistence and resume.
//
// The pipeline (docs/server.md, "Training jobs"):
//   1. "init": `<init_command> LOG_ABS_PATH --out WORK/scene.ply` as a child process, its output
//      in <job dir>/init.log, its exit code checked (init also writes WORK/scene.json);
//   2. "train", when the config asks for training (a preset, settings or max_iterations) and a
//      trainer exists: `<train_command> --log LOG_ABS_PATH --out WORK --preset P --set NAME=VALUE
//      ... [--resume]`, output in <job dir>/train.log, progress parsed from its stderr lines
//      ("I/N  loss L  psnr P dB  G Gaussians  R it/s  ETA H:MM:SS"); `--resume` is added when
//      WORK holds a trainer checkpoint (a re-run after a restart);
//   3. "publish": WORK/scene.json written if no stage wrote one, WORK renamed to
//      <state_dir>/scenes/<scene_name> (then loadable by name).
// The commands: `streetsim serve` passes its own binary's `init` / `train`; otherwise (tests
// linking the server) the `streetsim` next to this binary, train only if its help lists it.
// Unfinished jobs (QUEUED or RUNNING in their record) are re-queued at start; a stage that had
// finished is not run again.
#pragma once

#include <sys/types.h>

#include <condition_variable>
#include <deque>
#include <functional>
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
  std::vector<std::string> init_command;   // argv prefix; empty: {<exe dir>/streetsim, "init"}
  // argv prefix; empty: {<exe dir>/streetsim, "train"} if that binary's --help lists "train"
  // (probed once), else no train stage. Set: always used.
  std::vector<std::string> train_command;
};

// One "I/N  loss L  psnr P dB  G Gaussians  R it/s  ETA H:MM:SS" progress line of
// `streetsim train` (the bar before it, the rate and the ETA are optional).
struct TrainProgressLine {
  int64_t iteration = 0, total = 0;
  double loss = 0, psnr_db = 0;
  uint64_t gaussians = 0;
  double eta_s = -1;
};
bool ParseTrainProgressLine(const std::string& line, TrainProgressLine* out);

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
  // Whether jobs get a "train" stage: a trainer command was given, or `streetsim` beside this
  // binary has the train command (probed once).
  bool TrainAvailable();

 private:
  void WorkerLoop();
  void RunJob(const std::string& id);
  // RunJob's stages. Each returns the status the job fails (or stops) with; `work` is the scene
  // being built, `out_dir` where it is published.
  absl::Status InitStage(const std::string& id, const std::string& work, const std::string& out_dir,
                         const absl::StatusOr<std::string>& log, bool with_train, v1::Job* job);
  absl::Status TrainStage(const std::string& id, const std::string& work, const absl::StatusOr<std::string>& log,
                          v1::Job* job);
  absl::Status PublishStage(const std::string& work, const std::string& out_dir, int publish_index, v1::Job* job);
  // Runs argv as a child; returns its exit code, or CANCELLED / UNAVAILABLE (stopping). Each
  // new line the child writes to log_path goes to on_line (if set); it returns true when it
  // changed *job (the record is then written, at most every 250 ms).
  absl::StatusOr<int> RunChild(const std::string& id, const std::vector<std::string>& argv,
                               const std::string& log_path, v1::Job* job,
                               const std::function<bool(const std::string&)>& on_line = nullptr);
  // Whether the job gets a "train" stage (max_iterations > 0 and a trainer exists).
  bool WithTrain(const v1::Job& job);
  bool CancelRequested(const std::string& id);
  absl::Status CheckContinuation(const v1::CreateTrainingJobRequest& req, const std::string& from);

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
  std::mutex probe_mu_;
  int train_available_ = -1;  // -1: not probed yet
};

bool IsFinal(v1::JobState state);

}  // namespace streetsim::server
