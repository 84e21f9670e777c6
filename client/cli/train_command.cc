// streetsim train: a scene from a driving log, as its resolved config says (train_flags.h,
// scene/train/config/; docs/training.md).
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <csignal>
#include <cstdio>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "client/cli/parent_server.h"
#include "client/cli/train_flags.h"
#include "client/cli/train_schedule_runner.h"
#include "render/engine.h"
#include "scene/actors/scene_actors.h"
#include "scene/log/open_log.h"
#include "scene/log/scene_manifest.h"
#include "scene/train/clip_training.h"
#include "scene/train/config/run_config.h"
#include "scene/train/config/run_resolution.h"
#include "scene/train/run_dir_lock.h"
#include "scene/train/trainer.h"

namespace streetsim {
namespace {

int FailTrain(int code, const absl::Status& status) { return ReportFailure("train", code, status); }

std::string Duration(double s) {
  char buf[32];
  const int t = static_cast<int>(s + 0.5);
  std::snprintf(buf, sizeof(buf), "%d:%02d:%02d", t / 3600, (t / 60) % 60, t % 60);
  return buf;
}

// SIGINT / SIGTERM: the first stops the run after the iteration in progress with a checkpoint
// (a long fine stage loses nothing); a second one kills at once (the default action).
std::atomic<bool> g_stop_requested{false};
volatile std::sig_atomic_t g_stop_signal = 0;

void OnStopSignal(int sig) {
  if (g_stop_signal != 0) {
    std::signal(sig, SIG_DFL);
    std::raise(sig);
    return;
  }
  g_stop_signal = sig;
  g_stop_requested.store(true);
  static const char kMsg[] =
      "\nstreetsim train: stopping after this iteration with a checkpoint (again to kill now)\n";
  [[maybe_unused]] const ssize_t n = write(STDERR_FILENO, kMsg, sizeof(kMsg) - 1);
}

// SIGHUP: the server that started this trainer is gone (client/cli/parent_server.h). The kernel
// says so once for each of the server's threads as they end, so this one never escalates to a kill:
// the run stops after its iteration with a checkpoint that the restarted server resumes.
void OnParentGone(int sig) {
  if (g_stop_signal == 0) {
    g_stop_signal = sig;
    static const char kMsg[] = "\nstreetsim train: the server that started this run is gone: stopping with a checkpoint\n";
    [[maybe_unused]] const ssize_t n = write(STDERR_FILENO, kMsg, sizeof(kMsg) - 1);
  }
  g_stop_requested.store(true);
}

void InstallStopHandlers() {
  struct sigaction sa = {};
  sa.sa_handler = OnStopSignal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  struct sigaction hup = {};
  hup.sa_handler = OnParentGone;
  sigemptyset(&hup.sa_mask);
  sigaction(SIGHUP, &hup, nullptr);
}

int ExitCodeFor(const absl::Status& s) {
  const absl::StatusCode c = s.code();
  return c == absl::StatusCode::kInvalidArgument || c == absl::StatusCode::kNotFound ||
                 c == absl::StatusCode::kDataLoss || c == absl::StatusCode::kFailedPrecondition
             ? 2
             : 1;
}

// Which cameras train and how (docs/training.md "Grayscale cameras").
std::string CamerasSummary(const DriveLog& log, const train::config::Settings& settings) {
  bool rig_has_colour = false;
  for (const CameraSensor& c : log.cameras) rig_has_colour = rig_has_colour || c.colour;
  const std::string gray = settings.GetText("grayscale-cameras");
  std::string cams;
  for (const CameraSensor& c : log.cameras) {
    const std::string how = c.colour            ? "colour"
                            : !rig_has_colour   ? "grayscale, as it is"
                            : gray == "luminance" ? "grayscale, luminance only"
                            : gray == "skip"      ? "grayscale, left out"
                                                  : "grayscale, as colour";
    absl::StrAppend(&cams, cams.empty() ? "" : "; ", c.name, " ", how);
  }
  return cams;
}

std::string Describe(const train::config::ResolvedRun& run, const std::vector<train::config::Segment>& segments) {
  const train::config::Settings& last = segments.back().settings;
  const std::string field = last.GetText("field");
  std::string what = absl::StrCat(last.GetInt("iterations"), " iterations, ");
  if (field == "static") {
    absl::StrAppend(&what, "static model");
  } else {
    absl::StrAppend(&what, field == "extended" ? "the extended field" : "S3Gaussian's field", " after ",
                    last.GetInt("static-iterations"), " static");
  }
  if (segments.size() > 1) absl::StrAppend(&what, ", ", segments.size(), " stages");
  return absl::StrCat(run.config.preset.empty() ? "no preset" : "preset " + run.config.preset, " (", what, ")");
}

// The run's last stage (docs/actors.md): actors from the finished scene. Their failure costs the
// run nothing: the scene is written, and `streetsim actors extract` can try again. A run without
// them leaves no actors of an earlier scene behind (they would name another scene.ply's rows).
void ExtractActorsAtTheEnd(const DriveLog& log, const std::string& dir, const train::config::Settings& settings) {
  namespace fs = std::filesystem;
  if (!settings.GetBool("actors") || log.lidars.empty()) {
    std::error_code ec;
    fs::remove(fs::path(dir) / actors::kActorsJson, ec);
    fs::remove(fs::path(dir) / actors::kActorsPly, ec);
    return;
  }
  // A resumed run that had nothing left to do keeps the actors of its unchanged scene.
  if (actors::ReadActorSet(dir).ok()) return;
  absl::StatusOr<actors::ActorSet> set = actors::ExtractSceneActors(log, dir);
  if (!set.ok()) {
    std::fprintf(stderr, "streetsim train: warning: no actors: %s\n", std::string(set.status().message()).c_str());
    return;
  }
  size_t gaussians = 0;
  for (const actors::Actor& a : set->actors) gaussians += a.body_rows.size();
  std::fprintf(stderr, "streetsim train: %zu actors (%zu Gaussians) -> %s/%s\n", set->actors.size(), gaussians,
               dir.c_str(), actors::kActorsJson);
}

}  // namespace

int RunTrainCommand(const std::vector<std::string>& argv) {
  std::vector<FlagSpec> specs = {{"log"}, {"out"}, {"resume", false}, {"help", false}, {"help-all", false}};
  for (const FlagSpec& f : TrainSettingFlagSpecs()) specs.push_back(f);
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, specs);
  if (!args.ok()) return FailTrain(2, args.status());
  if (args->Has("help") || args->Has("help-all")) {
    std::fputs(TrainHelp(args->Has("help-all")).c_str(), stdout);
    return 0;
  }
  if (!args->positional().empty()) {
    return FailTrain(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  absl::StatusOr<std::string> log_path = args->Required("log");
  if (!log_path.ok()) return FailTrain(2, log_path.status());
  absl::StatusOr<std::string> out = args->Required("out");
  if (!out.ok()) return FailTrain(2, out.status());
  absl::StatusOr<train::config::CommandLineConfig> given = TrainCommandLineConfig(*args);
  if (!given.ok()) return FailTrain(2, given.status());
  // Everything the command line says is checked before the directory is locked or the log read.
  absl::StatusOr<train::config::ResolvedRun> run = train::config::ResolveRun(*out, args->Has("resume"), *given);
  if (!run.ok()) return FailTrain(2, run.status());
  std::vector<train::config::Segment> segments = train::config::Segments(run->config);

  // One writer per directory, held to the end. A server's trainer waits for its predecessor: after
  // a server restart the previous trainer of the same job may still be writing its last checkpoint.
  absl::StatusOr<train::RunDirLock> lock = train::RunDirLock::Acquire(*out, StartedByServer() ? 180 : 0);
  if (!lock.ok()) return FailTrain(2, lock.status());
  absl::StatusOr<DriveLog> log = OpenLog(*log_path);
  if (!log.ok()) return FailTrain(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  absl::StatusOr<bool> static_for_log = train::config::FitFieldToLog(*log, &*run);
  if (!static_for_log.ok()) return FailTrain(2, static_for_log.status());
  absl::StatusOr<bool> log_poses = train::config::FitPosesToLog(*log, &*run);
  if (!log_poses.ok()) return FailTrain(2, log_poses.status());
  segments = train::config::Segments(run->config);
  std::fprintf(stderr, "streetsim train: %s%s -> %s/config.json\n", run->resumes ? "resuming " : "",
               Describe(*run, segments).c_str(), out->c_str());
  std::fprintf(stderr, "streetsim train: cameras: %s\n", CamerasSummary(*log, segments.back().settings).c_str());
  if (*static_for_log) std::fprintf(stderr, "streetsim train: %s\n", train::config::kCameraOnlyStaticNote);
  if (*log_poses) std::fprintf(stderr, "streetsim train: %s\n", train::config::kImagePosesNote);
  if (run->migrated) {
    std::fprintf(stderr, "streetsim train: %s predates config.json: its settings were read from checkpoint.json\n",
                 out->c_str());
  }
  if (log->lidars.empty() && segments.back().settings.GetText("field") != "static" &&
      segments.back().settings.GetDouble("field-motion-prior") > 0 &&
      !segments.back().settings.given("field-motion-prior")) {
    std::fprintf(stderr, "streetsim train: the log has no LiDAR: the preset's motion prior is left out\n");
  }
  for (const std::string& c : run->changed) {
    std::fprintf(stderr, "streetsim train: from iteration %lld: %s\n", static_cast<long long>(run->done_iterations),
                 c.c_str());
  }
  const int64_t total = segments.back().end;
  const bool tty = isatty(fileno(stderr));
  auto progress = [&](const train::Progress& p) {
    const int width = 30;
    const int filled = static_cast<int>(width * p.iteration / std::max<int64_t>(1, total));
    std::string bar(filled, '#');
    bar.resize(width, '.');
    // The trainer's ETA is to its segment's end; the run's is to its own.
    const double eta_s = p.eta_static_stage_only || p.low_res_scale > 0 || p.it_per_s <= 0
                             ? p.eta_s
                             : (total - p.iteration) / p.it_per_s;
    std::fprintf(stderr, "%s[%s] %lld/%lld  loss %.4f  psnr %.2f dB  %zu Gaussians  %.2f it/s  ETA %s%s%s",
                 tty ? "\r" : "", bar.c_str(), static_cast<long long>(p.iteration), static_cast<long long>(total),
                 p.loss, p.psnr, p.gaussians, p.it_per_s, Duration(eta_s).c_str(),
                 p.low_res_scale > 0
                     ? absl::StrCat(" (low-resolution stage at scale ", p.low_res_scale, ")").c_str()
                 : p.eta_static_stage_only ? " (static stage; the fine stage is slower)"
                                           : "",
                 tty ? "" : "\n");
    std::fflush(stderr);
  };
  InstallStopHandlers();
  absl::StatusOr<train::ClipTrainResult> clips = RunSchedule(*log, *out, &g_stop_requested, progress, &*run);
  absl::StatusOr<train::TrainResult> r =
      !clips.ok() ? absl::StatusOr<train::TrainResult>(clips.status())
                  : clips->runs.empty() ? train::TrainResult{} : clips->runs.back().result;
  if (!r.ok() && absl::IsCancelled(r.status()) && g_stop_signal != 0) {
    return FailTrain(128 + g_stop_signal, r.status());  // 130 for SIGINT, 143 for SIGTERM, as a killed run
  }
  if (!r.ok()) return FailTrain(ExitCodeFor(r.status()), r.status());
  // The log's rig, time range and trajectory beside the scene, for `streetsim serve`.
  const std::filesystem::path out_dir(*out);
  if (absl::Status s = WriteSceneManifest(*log, std::filesystem::absolute(out_dir).filename().string(),
                                          (out_dir / "scene.json").string());
      !s.ok()) {
    return FailTrain(1, s);
  }
  if (clips->set) {
    for (const train::ClipRun& c : clips->runs) {
      std::fprintf(stderr,
                   "streetsim train: clip %d, frames [%d, %d) trained on [%d, %d): %lld iterations, %zu Gaussians, "
                   "%.1f s -> %s\n",
                   c.clip, c.frames.first_frame, c.frames.end_frame, c.trained.first_frame, c.trained.end_frame,
                   static_cast<long long>(c.result.iterations),
                   c.result.gaussians, c.result.seconds, c.dir.c_str());
      if (!c.result.heldout.frames.empty()) {
        std::fprintf(stderr, "streetsim train: clip %d held-out (%zu views): PSNR %.2f dB, SSIM %.4f\n", c.clip,
                     c.result.heldout.frames.size(), c.result.heldout.mean.psnr, c.result.heldout.mean.ssim);
      }
    }
    std::fprintf(stderr, "streetsim train: %zu clips -> %s/clips.json\n", clips->set->clips.size(), out->c_str());
    return 0;
  }
  ExtractActorsAtTheEnd(*log, *out, segments.back().settings);
  std::fprintf(stderr, "streetsim train: %lld iterations, %zu Gaussians, %.1f s -> %s/scene.ply\n",
               static_cast<long long>(r->iterations), r->gaussians, r->seconds, out->c_str());
  if (!r->heldout.frames.empty()) {
    std::fprintf(stderr, "streetsim train: held-out (%zu views): PSNR %.2f dB, SSIM %.4f\n", r->heldout.frames.size(),
                 r->heldout.mean.psnr, r->heldout.mean.ssim);
  }
  if (r->seconds_to_psnr24 >= 0) {
    std::fprintf(stderr, "streetsim train: training-view PSNR (50-view mean) reached 24 dB after %.1f s\n",
                 r->seconds_to_psnr24);
  }
  return 0;
}

}  // namespace streetsim
