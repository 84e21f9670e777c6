#include "server/job_runner.h"

#include <sys/wait.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <regex>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "server/child_process.h"
#include "server/echo.h"
#include "server/path_confinement.h"
#include "server/replica.h"
#include "server/request_identity.h"
#include "server/scene_manifest.h"
#include "server/trained_outputs.h"
#include "server/training_config.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {

// Stages: init, [train,] publish. stage_index: 0 init, 1 train (or publish), 2 publish.
int NumStages(bool with_train) { return with_train ? 3 : 2; }
// Job fraction when init / train end.
double InitDoneFraction(bool with_train) { return with_train ? 0.05 : 0.9; }
constexpr double kTrainDoneFraction = 0.95;

std::string StreetsimNextToThisBinary() {
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  return (exe.parent_path() / "streetsim").string();
}

// How often one attempt of a job restarts a trainer that something outside the server killed.
constexpr int kMaxTrainerRestarts = 3;

}  // namespace

bool ParseTrainProgressLine(const std::string& line, TrainProgressLine* out) {
  static const std::regex kLine(
      R"((\d+)/(\d+)\s+loss\s+(\S+)\s+psnr\s+(\S+)\s+dB\s+(\d+)\s+Gaussians(?:\s+\S+\s+it/s)?(?:\s+ETA\s+(\d+):(\d+):(\d+))?)");
  std::smatch m;
  if (!std::regex_search(line, m, kLine)) return false;
  TrainProgressLine p;
  if (!absl::SimpleAtoi(m[1].str(), &p.iteration) || !absl::SimpleAtoi(m[2].str(), &p.total) ||
      !absl::SimpleAtod(m[3].str(), &p.loss) || !absl::SimpleAtod(m[4].str(), &p.psnr_db) ||
      !absl::SimpleAtoi(m[5].str(), &p.gaussians) || p.total <= 0 || p.iteration < 0) {
    return false;
  }
  if (m[6].matched) {
    int h = 0, mi = 0, sec = 0;
    if (absl::SimpleAtoi(m[6].str(), &h) && absl::SimpleAtoi(m[7].str(), &mi) && absl::SimpleAtoi(m[8].str(), &sec)) {
      p.eta_s = h * 3600.0 + mi * 60.0 + sec;
    }
  }
  *out = p;
  return true;
}

bool IsFinal(v1::JobState s) {
  return s == v1::JOB_STATE_SUCCEEDED || s == v1::JOB_STATE_FAILED || s == v1::JOB_STATE_CANCELLED;
}

JobRunner::JobRunner(JobStore* store, ServiceDeps* deps, JobRunnerOptions options)
    : store_(store), deps_(deps), options_(std::move(options)) {
  if (options_.init_command.empty()) options_.init_command = {StreetsimNextToThisBinary(), "init"};
  if (!options_.train_command.empty()) train_available_ = 1;
}

bool JobRunner::TrainAvailable() {
  std::lock_guard<std::mutex> lock(probe_mu_);
  if (train_available_ < 0) {
    const std::string program = StreetsimNextToThisBinary();
    train_available_ = HelpListsCommand(program, "train") ? 1 : 0;
    if (train_available_) options_.train_command = {program, "train"};
    LOG(INFO) << "training jobs: " << (train_available_ ? "" : "no ") << "train stage (" << program << " --help)";
  }
  return train_available_ == 1;
}

bool JobRunner::WithTrain(const v1::Job& job) { return AsksTraining(job.config()) && TrainAvailable(); }

JobRunner::~JobRunner() { Stop(); }

void JobRunner::Start() {
  for (v1::Job job : store_->List()) {
    if (IsFinal(job.state())) continue;
    job.set_state(v1::JOB_STATE_QUEUED);
    if (!store_->Put(job).ok()) continue;
    LOG(INFO) << "resuming job " << job.job_id() << " (stage " << job.progress().stage_index() << ")";
    std::lock_guard<std::mutex> lock(mu_);
    queue_.push_back(job.job_id());
  }
  std::lock_guard<std::mutex> lock(mu_);
  for (int i = 0; i < std::max(1, deps_->limits.max_concurrent_jobs); ++i) {
    workers_.emplace_back([this] { WorkerLoop(); });
  }
}

void JobRunner::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (stopping_ && workers_.empty()) return;
    stopping_ = true;
  }
  cv_.notify_all();
  for (std::thread& t : workers_) t.join();
  workers_.clear();
}

int JobRunner::running() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(running_.size());
}

bool JobRunner::CancelRequested(const std::string& id) {
  std::lock_guard<std::mutex> lock(mu_);
  return cancel_requested_.count(id) > 0;
}

absl::StatusOr<v1::Job> JobRunner::Create(const v1::CreateTrainingJobRequest& req) {
  if (deps_->draining) return absl::UnavailableError("server is shutting down");
  if (!req.request_id().empty()) {
    if (std::optional<v1::Job> existing = store_->FindByRequestId(req.request_id())) {
      if (existing->log_path() != req.log_path() || Fingerprint(existing->config()) != Fingerprint(req.config())) {
        return RequestIdReused(req.request_id(), "training job");
      }
      return *existing;
    }
  }
  absl::StatusOr<std::string> log = ResolveUnderRoot(options_.data_root, req.log_path());
  if (!log.ok()) return absl::Status(log.status().code(), absl::StrCat("log_path: ", log.status().message()));
  if (absl::Status s = ValidateTrainingConfig(req.config()); !s.ok()) return s;
  if (store_->size() >= deps_->limits.max_jobs) {
    return absl::ResourceExhaustedError(absl::StrCat("job limit reached (", deps_->limits.max_jobs, ")"));
  }
  v1::Job job;
  job.set_job_id(store_->NewId());
  std::string name = req.config().scene_name().empty() ? "job-" + job.job_id() : req.config().scene_name();
  if (!IsSceneName(name)) {
    return absl::InvalidArgumentError("config.scene_name: 1-64 of [A-Za-z0-9_.-], not starting with '.'");
  }
  if (deps_->scenes && deps_->scenes->Exists(name)) {
    return absl::AlreadyExistsError(absl::StrCat("a scene named ", Echo(name), " already exists"));
  }
  for (const v1::Job& other : store_->List()) {
    if (other.scene_name() == name && other.state() != v1::JOB_STATE_FAILED &&
        other.state() != v1::JOB_STATE_CANCELLED) {
      return absl::AlreadyExistsError(absl::StrCat("job ", other.job_id(), " already produces scene ", Echo(name)));
    }
  }
  if (const std::string& from = req.config().continue_from_scene(); !from.empty()) {
    if (absl::Status s = CheckContinuation(req, from); !s.ok()) return s;
  }
  job.set_log_path(req.log_path());
  *job.mutable_config() = req.config();
  job.set_request_id(req.request_id());
  job.set_state(v1::JOB_STATE_QUEUED);
  job.set_scene_name(name);
  job.set_created_unix_ms(NowUnixMs());
  v1::JobProgress* p = job.mutable_progress();
  p->set_stage("init");
  p->set_num_stages(NumStages(WithTrain(job)));
  p->set_max_iterations(req.config().max_iterations());
  p->set_eta_s(-1);
  if (absl::Status s = store_->Put(job); !s.ok()) return s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    queue_.push_back(job.job_id());
  }
  cv_.notify_one();
  return job;
}

// A job's scene that another job may continue: trained by this server from the same log, with a
// checkpoint to resume, and fewer iterations than the new job asks for.
absl::Status JobRunner::CheckContinuation(const v1::CreateTrainingJobRequest& req, const std::string& from) {
  if (!TrainAvailable()) {
    return absl::FailedPreconditionError("config.continue_from_scene: this server's build has no `streetsim train`");
  }
  const v1::Job* source = nullptr;
  const std::vector<v1::Job> jobs = store_->List();
  for (const v1::Job& j : jobs) {
    if (j.scene_name() == from && j.state() == v1::JOB_STATE_SUCCEEDED) source = &j;
  }
  if (!source) {
    return absl::NotFoundError(absl::StrCat("config.continue_from_scene: no finished job of this server trained a scene '",
                                            from, "'"));
  }
  const absl::StatusOr<std::string> source_log = ResolveUnderRoot(options_.data_root, source->log_path());
  const absl::StatusOr<std::string> log = ResolveUnderRoot(options_.data_root, req.log_path());
  if (!source_log.ok() || !log.ok() || *source_log != *log) {
    return absl::InvalidArgumentError(absl::StrCat("config.continue_from_scene: ", Echo(from), " was trained from log_path '",
                                                   source->log_path(), "', not ", Echo(req.log_path())));
  }
  const std::string dir = store_->scenes_dir() + "/" + from;
  if (!HasTrainerCheckpoint(dir)) {
    return absl::FailedPreconditionError(
        absl::StrCat("config.continue_from_scene: scene ", Echo(from), " has no checkpoint to continue from"));
  }
  absl::StatusOr<train::SceneMeta> meta = TrainedSceneMeta(dir);
  if (!meta.ok()) {
    return absl::FailedPreconditionError(absl::StrCat("config.continue_from_scene: ", meta.status().message()));
  }
  const v1::TrainingConfig& c = req.config();
  if (c.field().empty() && meta->field == "static" &&
      (c.has_static_iterations() || c.field_lr_scale() != 0 || c.field_lr_decay_iterations() != 0 ||
       c.has_field_motion_prior() || !c.field_motion_prior_scans().empty())) {
    return absl::InvalidArgumentError(
        absl::StrCat("config: scene '", from,
                     "' is a static scene: static_iterations, field_lr_*, field_motion_prior and "
                     "field_motion_prior_scans need a field (config.field)"));
  }
  // The iterations asked for: the settings' (as text, checked by ValidateTrainingConfig), else
  // the deprecated max_iterations; neither: the scene's own, which cannot be above its own.
  int64_t asked = c.max_iterations();
  if (auto it = c.settings().find("iterations"); it != c.settings().end()) (void)absl::SimpleAtoi(it->second, &asked);
  if (meta->iterations >= asked) {
    return absl::InvalidArgumentError(absl::StrCat("config iterations (", asked,
                                                   ") must be above the ", meta->iterations, " iterations scene '",
                                                   from, "' was trained for"));
  }
  return absl::OkStatus();
}

absl::StatusOr<v1::Job> JobRunner::Cancel(const std::string& id) {
  std::optional<v1::Job> job = store_->Get(id);
  if (!job) return absl::NotFoundError(absl::StrCat("unknown job ", Echo(id)));
  if (IsFinal(job->state())) return *job;
  if (!store_->Owns(id)) {
    return absl::FailedPreconditionError(absl::StrCat("job ", Echo(id), " is run by replica ",
                                                      Echo(std::string(ReplicaOfId(id))),
                                                      "; send CancelJob to that replica"));
  }
  bool is_running;
  {
    std::lock_guard<std::mutex> lock(mu_);
    cancel_requested_.insert(id);
    is_running = running_.count(id) > 0;
    if (!is_running) {
      for (auto it = queue_.begin(); it != queue_.end(); ++it) {
        if (*it == id) { queue_.erase(it); break; }
      }
    }
  }
  if (!is_running) {
    job->set_state(v1::JOB_STATE_CANCELLED);
    if (absl::Status s = store_->Put(*job); !s.ok()) return s;
    return *job;
  }
  // The worker notices within ~50 ms; wait briefly so the reply usually shows the final state.
  for (int i = 0; i < 100; ++i) {
    std::optional<v1::Job> now = store_->Get(id);
    if (now && IsFinal(now->state())) return *now;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return *store_->Get(id);
}

void JobRunner::WorkerLoop() {
  while (true) {
    std::string id;
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait(lock, [&] { return stopping_ || !queue_.empty(); });
      if (stopping_) return;
      id = queue_.front();
      queue_.pop_front();
      running_.insert(id);
    }
    RunJob(id);
    std::lock_guard<std::mutex> lock(mu_);
    running_.erase(id);
    cancel_requested_.erase(id);
  }
}

absl::StatusOr<int> JobRunner::RunChild(const std::string& id, const std::vector<std::string>& argv,
                                        const std::string& log_path, v1::Job* job,
                                        const std::function<bool(const std::string&)>& on_line) {
  LogTail tail(log_path, on_line);
  absl::StatusOr<pid_t> spawned = SpawnLoggedChild(argv, log_path);
  if (!spawned.ok()) return spawned.status();
  const pid_t pid = *spawned;
  bool dirty = false;

  const auto t0 = std::chrono::steady_clock::now();
  auto last_update = t0, last_read = t0;
  const double elapsed_before = job->progress().elapsed_s();
  while (true) {
    int wstatus = 0;
    const pid_t r = waitpid(pid, &wstatus, WNOHANG);
    if (r == pid) {
      tail.Flush();
      if (WIFEXITED(wstatus)) return WEXITSTATUS(wstatus);
      return 128 + (WIFSIGNALED(wstatus) ? WTERMSIG(wstatus) : 0);
    }
    bool stop, cancel;
    {
      std::lock_guard<std::mutex> lock(mu_);
      stop = stopping_;
      cancel = cancel_requested_.count(id) > 0;
    }
    if (stop || cancel) {
      // On SIGTERM `streetsim train` finishes its iteration and writes a checkpoint (docs/training.md
      // "CLI"). A server stop leaves the job to resume at the next start, so it gets the time for
      // that (a KITTI fine iteration plus ~1 GB of checkpoint); a cancelled job is not resumed and
      // gets 2 s.
      EndChildGroup(pid, cancel ? 2000 : 30000);
      return cancel ? absl::CancelledError("cancelled") : absl::UnavailableError("server stopping");
    }
    const auto now = std::chrono::steady_clock::now();
    if (now - last_read > std::chrono::milliseconds(100)) {
      last_read = now;
      if (tail.Read()) dirty = true;
    }
    if (now - last_update > std::chrono::seconds(1) || (dirty && now - last_update > std::chrono::milliseconds(250))) {
      last_update = now;
      dirty = false;
      job->mutable_progress()->set_elapsed_s(elapsed_before + std::chrono::duration<double>(now - t0).count());
      (void)store_->Put(*job);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

// RunJob's first stage (skipped when a previous attempt finished it): the initial scene in `work`.
absl::Status JobRunner::InitStage(const std::string& id, const std::string& work, const std::string& out_dir,
                                  const absl::StatusOr<std::string>& log, bool with_train, v1::Job* job) {
  v1::JobProgress* p = job->mutable_progress();
  std::error_code ec;
  // A continuation's init is a copy of the scene it continues (its checkpoint, outputs and
  // manifest); the source stays as it is.
  if (p->stage_index() < 1 && !fs::exists(out_dir) && !job->config().continue_from_scene().empty()) {
    p->set_stage("init");
    (void)store_->Put(*job);
    const std::string from = store_->scenes_dir() + "/" + job->config().continue_from_scene();
    if (!HasTrainerCheckpoint(from)) {
      return absl::FailedPreconditionError(absl::StrCat("scene '", job->config().continue_from_scene(),
                                                        "' is gone or has no checkpoint"));
    }
    fs::copy(from, work, fs::copy_options::recursive | fs::copy_options::overwrite_existing, ec);
    if (ec) return absl::InternalError(absl::StrCat("cannot copy scene '", job->config().continue_from_scene(),
                                                    "': ", ec.message()));
    p->set_stage_index(1);
    p->set_fraction(InitDoneFraction(with_train));
    p->set_num_gaussians(TrainedGaussianCount(work));
    (void)store_->Put(*job);
  }
  if (p->stage_index() < 1 && !fs::exists(out_dir)) {
    p->set_stage("init");
    (void)store_->Put(*job);
    if (!log.ok()) return log.status();
    std::vector<std::string> argv = options_.init_command;
    argv.insert(argv.end(), {*log, "--out", work + "/scene.ply"});
    absl::StatusOr<int> code = RunChild(id, argv, store_->JobDir(id) + "/init.log", job);
    if (!code.ok()) return code.status();
    if (*code != 0) {
      return absl::InternalError(absl::StrCat("init stage exited with code ", *code, " (see ",
                                              store_->JobDir(id), "/init.log)"));
    }
    if (!fs::exists(work + "/scene.ply")) return absl::InternalError("init stage wrote no scene.ply");
    p->set_stage_index(1);
    p->set_fraction(InitDoneFraction(with_train));
    p->set_num_gaussians(PlyVertexCount(work + "/scene.ply"));
    (void)store_->Put(*job);
  }
  return absl::OkStatus();
}

// RunJob's train stage (when asked for and available). Re-run after a restart with --resume when
// the trainer left a checkpoint; WORK/scene.json (from init) is left alone by the trainer.
absl::Status JobRunner::TrainStage(const std::string& id, const std::string& work,
                                   const absl::StatusOr<std::string>& log, v1::Job* job) {
  v1::JobProgress* p = job->mutable_progress();
  p->set_stage("train");
  p->set_max_iterations(job->config().max_iterations());
  (void)store_->Put(*job);
  if (!log.ok()) return log.status();
  std::vector<std::string> argv = options_.train_command;
  argv.insert(argv.end(), {"--log", *log, "--out", work});
  const std::vector<std::string> flags = TrainFlags(job->config());
  argv.insert(argv.end(), flags.begin(), flags.end());
  std::string trainer_message;  // its last "streetsim train: ..." line: why it failed, if it does
  auto on_line = [&](const std::string& line) {
    if (line.rfind("streetsim train: ", 0) == 0) trainer_message = line.substr(17, 512);
    // The divergence guard's rollbacks (docs/training.md "Divergence guard"), for the job's client.
    if (line.rfind("streetsim train: iteration ", 0) == 0 && line.find("rolled back") != std::string::npos &&
        p->notes_size() < 16) {
      p->add_notes(line.substr(17, 512));
      return true;  // a change to the record, stored with the progress
    }
    TrainProgressLine t;
    if (!ParseTrainProgressLine(line, &t)) return false;
    p->set_iteration(t.iteration);
    p->set_max_iterations(t.total);
    p->set_has_metrics(true);
    if (std::isfinite(t.loss)) p->set_loss(t.loss);
    if (std::isfinite(t.psnr_db)) p->set_psnr_db(t.psnr_db);
    p->set_num_gaussians(t.gaussians);
    p->set_eta_s(t.eta_s);
    const double f = std::clamp(static_cast<double>(t.iteration) / static_cast<double>(t.total), 0.0, 1.0);
    p->set_fraction(InitDoneFraction(true) + (kTrainDoneFraction - InitDoneFraction(true)) * f);
    return true;
  };
  // A trainer killed from outside (the OOM killer, an operator's kill -9) goes on from its last
  // checkpoint, a bounded number of times: it loses at most one checkpoint interval.
  absl::StatusOr<int> code;
  for (int restart = 0;; ++restart) {
    std::vector<std::string> run = argv;
    if (HasTrainerCheckpoint(work)) run.push_back("--resume");
    code = RunChild(id, run, store_->JobDir(id) + "/train.log", job, on_line);
    if (!code.ok() || *code != 128 + SIGKILL || restart == kMaxTrainerRestarts) break;
    LOG(WARNING) << "job " << id << ": the trainer was killed (SIGKILL); resuming it from its last checkpoint";
  }
  if (!code.ok()) return code.status();
  if (*code != 0) {
    return absl::InternalError(absl::StrCat("train stage exited with code ", *code,
                                            trainer_message.empty() ? "" : ": ", trainer_message, " (see ",
                                            store_->JobDir(id), "/train.log)"));
  }
  if (!fs::exists(work + "/scene.ply")) return absl::InternalError("train stage left no scene.ply");
  p->set_stage_index(2);
  p->set_fraction(kTrainDoneFraction);
  // The trainer prints progress every few iterations, so its last line can lag the end (or, for a
  // short run, be its first iteration): a finished stage reports what the scene records.
  if (absl::StatusOr<train::SceneMeta> meta = TrainedSceneMeta(work); meta.ok() && meta->iterations > 0) {
    p->set_iteration(meta->iterations);
    p->set_max_iterations(meta->iterations);
  } else {
    p->set_iteration(p->max_iterations());
  }
  p->set_num_gaussians(TrainedGaussianCount(work));
  *job->mutable_heldout() = TrainedHeldoutMetrics(work);
  p->set_preview_png(FirstPreviewPng(work));
  (void)store_->Put(*job);
  return absl::OkStatus();
}

// RunJob's last stage: `work` becomes the published scene `out_dir`.
absl::Status JobRunner::PublishStage(const std::string& work, const std::string& out_dir, int publish_index,
                                     v1::Job* job) {
  v1::JobProgress* p = job->mutable_progress();
  std::error_code ec;
  p->set_stage_index(publish_index);
  p->set_stage("publish");
  if (!fs::exists(work + "/scene.json")) {
    SceneManifest m;
    m.cameras = DefaultRig();
    std::ofstream(work + "/scene.json") << SceneManifestToJson(m);
  }
  fs::rename(work, out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot publish the scene: ", ec.message()));
  return absl::OkStatus();
}

void JobRunner::RunJob(const std::string& id) {
  std::optional<v1::Job> loaded = store_->Get(id);
  if (!loaded || IsFinal(loaded->state())) return;
  v1::Job job = *loaded;
  if (CancelRequested(id)) {
    job.set_state(v1::JOB_STATE_CANCELLED);
    (void)store_->Put(job);
    return;
  }
  job.set_state(v1::JOB_STATE_RUNNING);
  job.set_attempts(job.attempts() + 1);
  (void)store_->Put(job);
  const auto t0 = std::chrono::steady_clock::now();
  const double elapsed_before = job.progress().elapsed_s();
  auto fail = [&](const absl::Status& s) {
    if (absl::IsCancelled(s)) {
      job.set_state(v1::JOB_STATE_CANCELLED);
    } else if (absl::IsUnavailable(s)) {
      job.set_state(v1::JOB_STATE_RUNNING);  // stopping: stays unfinished, resumed at next start
    } else {
      job.set_state(v1::JOB_STATE_FAILED);
      job.set_error(std::string(s.message()));
    }
    (void)store_->Put(job);
    LOG(INFO) << "job " << id << ": " << s.message();
  };

  const std::string work = store_->JobDir(id) + "/work";
  const std::string out_dir = store_->scenes_dir() + "/" + job.scene_name();
  std::error_code ec;
  fs::create_directories(work, ec);
  v1::JobProgress* p = job.mutable_progress();

  const bool with_train = WithTrain(job);
  const int publish_index = NumStages(with_train) - 1;
  p->set_num_stages(NumStages(with_train));
  if (AsksTraining(job.config()) && !with_train) {
    LOG(WARNING) << "job " << id << ": training asked for, but this build has no `streetsim train`: init only";
  }
  absl::StatusOr<std::string> log = ResolveUnderRoot(options_.data_root, job.log_path());

  if (absl::Status s = InitStage(id, work, out_dir, log, with_train, &job); !s.ok()) return fail(s);
  if (with_train && p->stage_index() < 2 && !fs::exists(out_dir)) {
    if (absl::Status s = TrainStage(id, work, log, &job); !s.ok()) return fail(s);
  }
  if (!fs::exists(out_dir)) {
    if (absl::Status s = PublishStage(work, out_dir, publish_index, &job); !s.ok()) return fail(s);
  }
  p->set_stage("done");
  p->set_stage_index(NumStages(with_train));
  p->set_fraction(1.0);
  p->set_eta_s(0);
  p->set_elapsed_s(elapsed_before + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  if (p->num_gaussians() == 0) p->set_num_gaussians(PlyVertexCount(out_dir + "/scene.ply"));
  job.set_state(v1::JOB_STATE_SUCCEEDED);
  (void)store_->Put(job);
  LOG(INFO) << "job " << id << " succeeded: scene " << job.scene_name();
}

}  // namespace streetsim::server
