#include "server/job_runner.h"

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <regex>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "server/path_confinement.h"
#include "server/scene_manifest.h"

extern char** environ;

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {

constexpr int kNumStages = 2;  // init, publish (train will be added between them)

// "element vertex N" from a PLY header; 0 if unreadable.
uint64_t PlyVertexCount(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::string line;
  for (int i = 0; i < 64 && std::getline(in, line); ++i) {
    if (line.rfind("element vertex ", 0) == 0) {
      uint64_t n = 0;
      if (absl::SimpleAtoi(line.substr(15), &n)) return n;
    }
    if (line.rfind("end_header", 0) == 0) break;
  }
  return 0;
}

std::vector<std::string> DefaultInitCommand() {
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  return {(exe.parent_path() / "streetsim").string(), "init"};
}

}  // namespace

bool IsFinal(v1::JobState s) {
  return s == v1::JOB_STATE_SUCCEEDED || s == v1::JOB_STATE_FAILED || s == v1::JOB_STATE_CANCELLED;
}

JobRunner::JobRunner(JobStore* store, ServiceDeps* deps, JobRunnerOptions options)
    : store_(store), deps_(deps), options_(std::move(options)) {
  if (options_.init_command.empty()) options_.init_command = DefaultInitCommand();
}

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
    if (std::optional<v1::Job> existing = store_->FindByRequestId(req.request_id())) return *existing;
  }
  absl::StatusOr<std::string> log = ResolveUnderRoot(options_.data_root, req.log_path());
  if (!log.ok()) return absl::Status(log.status().code(), absl::StrCat("log_path: ", log.status().message()));
  if (req.config().max_iterations() < 0) return absl::InvalidArgumentError("config.max_iterations must be >= 0");
  if (store_->size() >= deps_->limits.max_jobs) {
    return absl::ResourceExhaustedError(absl::StrCat("job limit reached (", deps_->limits.max_jobs, ")"));
  }
  v1::Job job;
  job.set_job_id(store_->NewId());
  std::string name = req.config().scene_name().empty() ? "job-" + job.job_id() : req.config().scene_name();
  static const std::regex kName("[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}");
  if (!std::regex_match(name, kName)) {
    return absl::InvalidArgumentError("config.scene_name: 1-64 of [A-Za-z0-9_.-], not starting with '.'");
  }
  if (deps_->scenes && deps_->scenes->Exists(name)) {
    return absl::AlreadyExistsError(absl::StrCat("a scene named '", name, "' already exists"));
  }
  for (const v1::Job& other : store_->List()) {
    if (other.scene_name() == name && other.state() != v1::JOB_STATE_FAILED &&
        other.state() != v1::JOB_STATE_CANCELLED) {
      return absl::AlreadyExistsError(absl::StrCat("job ", other.job_id(), " already produces scene '", name, "'"));
    }
  }
  job.set_log_path(req.log_path());
  *job.mutable_config() = req.config();
  job.set_request_id(req.request_id());
  job.set_state(v1::JOB_STATE_QUEUED);
  job.set_scene_name(name);
  job.set_created_unix_ms(NowUnixMs());
  v1::JobProgress* p = job.mutable_progress();
  p->set_stage("init");
  p->set_num_stages(kNumStages);
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

absl::StatusOr<v1::Job> JobRunner::Cancel(const std::string& id) {
  std::optional<v1::Job> job = store_->Get(id);
  if (!job) return absl::NotFoundError(absl::StrCat("unknown job '", id, "'"));
  if (IsFinal(job->state())) return *job;
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
                                        const std::string& log_path, v1::Job* job) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 1, log_path.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
  posix_spawn_file_actions_adddup2(&actions, 1, 2);
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t none;
  sigemptyset(&none);
  posix_spawnattr_setsigmask(&attr, &none);  // the server blocks SIGTERM in its threads
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETPGROUP);
  posix_spawnattr_setpgroup(&attr, 0);
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  pid_t pid = 0;
  const int rc = posix_spawn(&pid, args[0], &actions, &attr, args.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attr);
  if (rc != 0) return absl::FailedPreconditionError(absl::StrCat("cannot start ", argv[0], ": ", strerror(rc)));

  const auto t0 = std::chrono::steady_clock::now();
  auto last_update = t0;
  const double elapsed_before = job->progress().elapsed_s();
  while (true) {
    int wstatus = 0;
    const pid_t r = waitpid(pid, &wstatus, WNOHANG);
    if (r == pid) {
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
      kill(-pid, SIGTERM);
      for (int i = 0; i < 100 && waitpid(pid, &wstatus, WNOHANG) == 0; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      }
      if (waitpid(pid, &wstatus, WNOHANG) == 0) {
        kill(-pid, SIGKILL);
        waitpid(pid, &wstatus, 0);
      }
      return cancel ? absl::CancelledError("cancelled") : absl::UnavailableError("server stopping");
    }
    const auto now = std::chrono::steady_clock::now();
    if (now - last_update > std::chrono::seconds(1)) {
      last_update = now;
      job->mutable_progress()->set_elapsed_s(elapsed_before + std::chrono::duration<double>(now - t0).count());
      (void)store_->Put(*job);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
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

  // Stage 0: init (skipped when a previous attempt finished it).
  if (p->stage_index() < 1 && !fs::exists(out_dir)) {
    p->set_stage("init");
    (void)store_->Put(job);
    absl::StatusOr<std::string> log = ResolveUnderRoot(options_.data_root, job.log_path());
    if (!log.ok()) return fail(log.status());
    std::vector<std::string> argv = options_.init_command;
    argv.insert(argv.end(), {*log, "--out", work + "/scene.ply"});
    absl::StatusOr<int> code = RunChild(id, argv, store_->JobDir(id) + "/init.log", &job);
    if (!code.ok()) return fail(code.status());
    if (*code != 0) {
      return fail(absl::InternalError(absl::StrCat("init stage exited with code ", *code, " (see ",
                                                   store_->JobDir(id), "/init.log)")));
    }
    if (!fs::exists(work + "/scene.ply")) return fail(absl::InternalError("init stage wrote no scene.ply"));
    p->set_stage_index(1);
    p->set_fraction(0.9);
    p->set_num_gaussians(PlyVertexCount(work + "/scene.ply"));
    (void)store_->Put(job);
  }
  // (The "train" stage goes here once scene/train exists.)
  // Stage 1: publish.
  if (!fs::exists(out_dir)) {
    p->set_stage("publish");
    if (!fs::exists(work + "/scene.json")) {
      SceneManifest m;
      m.cameras = DefaultRig();
      std::ofstream(work + "/scene.json") << SceneManifestToJson(m);
    }
    fs::rename(work, out_dir, ec);
    if (ec) return fail(absl::InternalError(absl::StrCat("cannot publish the scene: ", ec.message())));
  }
  p->set_stage("done");
  p->set_stage_index(kNumStages);
  p->set_fraction(1.0);
  p->set_eta_s(0);
  p->set_elapsed_s(elapsed_before + std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  if (p->num_gaussians() == 0) p->set_num_gaussians(PlyVertexCount(out_dir + "/scene.ply"));
  job.set_state(v1::JOB_STATE_SUCCEEDED);
  (void)store_->Put(job);
  LOG(INFO) << "job " << id << " succeeded: scene " << job.scene_name();
}

}  // namespace streetsim::server
