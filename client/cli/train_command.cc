// streetsim train: static 3DGS training of a driving log (docs/training.md).
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <functional>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "client/cli/parent_server.h"
#include "render/engine.h"
#include "scene/log/open_log.h"
#include "scene/log/scene_manifest.h"
#include "scene/train/clip_training.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/resolution_schedule.h"
#include "scene/train/run_dir_lock.h"
#include "scene/train/train_state.h"
#include "scene/train/trainer.h"

namespace streetsim {
namespace {

int Fail(int code, const absl::Status& status) { return ReportFailure("train", code, status); }

// --field-lr-scale's default (docs/training.md "Field learning rates").
constexpr double kDefaultFieldLrScale = 10;

std::string Duration(double s) {
  char buf[32];
  const int t = static_cast<int>(s + 0.5);
  std::snprintf(buf, sizeof(buf), "%d:%02d:%02d", t / 3600, (t / 60) % 60, t % 60);
  return buf;
}

// --field's default (issue 5: "the best measured"; docs/training.md "Default field"): S3Gaussian's
// field when the run is longer than its static warm-up (--static-iterations, 5000), static
// otherwise: a run too short for a fine stage gains nothing from the field. A resumed run keeps the
// field it was trained with, as its checkpoint.json records; in directories without one, field
// checkpoints mark a dynamic run, and a checkpoint past the warm-up without one a static run.
absl::StatusOr<train::FieldMode> DefaultFieldMode(const ParsedArgs& args, int64_t iterations, int static_iterations,
                                                  const std::string& out_dir) {
  if (args.Get("static-iterations")) {
    // An explicit warm-up asks for the staged run (its value is checked below).
    return train::FieldMode::kS3Gaussian;
  }
  namespace fs = std::filesystem;
  const fs::path ckpt = fs::path(out_dir) / "checkpoint.bin";
  std::error_code ec;
  if (args.Has("resume") && fs::exists(ckpt, ec)) {
    const absl::Status extended_run = absl::FailedPreconditionError(
        absl::StrCat(out_dir, " holds a --field extended run: resume it with --field extended and its --field-modules"));
    if (absl::StatusOr<std::string> recorded = train::ReadCheckpointField(out_dir); recorded.ok()) {
      if (*recorded == "extended") return extended_run;
      return train::ParseFieldMode(*recorded);
    } else if (!absl::IsNotFound(recorded.status())) {
      return recorded.status();
    }
    // Directories from before checkpoint.json: inferred from their files.
    const train::FieldCheckpointsFound found = train::FindFieldCheckpoints(out_dir);
    if (found.extended) return extended_run;
    if (found.base) return train::FieldMode::kS3Gaussian;
    absl::StatusOr<int64_t> done = train::PeekCheckpointIteration(ckpt.string());
    if (!done.ok()) return done.status();
    if (*done > static_iterations) return train::FieldMode::kStatic;
  }
  return iterations > static_iterations ? train::FieldMode::kS3Gaussian : train::FieldMode::kStatic;
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

// A learning-rate schedule's pair of flags, `--PREFIX-scale S` ((0, 1000]) and
// `--PREFIX-decay-iterations N` (1..10^7): the given ones into *scale / *decay_iterations.
absl::Status ParseLrScheduleFlags(const ParsedArgs& args, const std::string& prefix, double* scale,
                                  int* decay_iterations) {
  if (auto v = args.Get(prefix + "-scale"); v && (!absl::SimpleAtod(*v, scale) || !(*scale > 0 && *scale <= 1000))) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", prefix, "-scale must be a number in (0, 1000], not '", *v, "'"));
  }
  if (auto v = args.Get(prefix + "-decay-iterations");
      v && (!absl::SimpleAtoi(*v, decay_iterations) || *decay_iterations < 1 || *decay_iterations > 10'000'000)) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", prefix, "-decay-iterations must be an integer in 1..10000000, not '", *v, "'"));
  }
  return absl::OkStatus();
}

// A resumed run keeps its recorded schedule value by value: a flag given wins over its value only
// (annealing is `--resume --PREFIX-decay-iterations N` alone, which must not reset the scale).
void KeepRecordedLrSchedule(const ParsedArgs& args, const std::string& prefix, const train::FieldLrSchedule& recorded,
                            double* scale, int* decay_iterations) {
  if (!args.Has(prefix + "-scale")) *scale = recorded.scale;
  if (!args.Has(prefix + "-decay-iterations")) *decay_iterations = recorded.decay_iterations;
}

// An integer setting a checkpoint records (e.g. --position-lr-decay-iterations, --densify-until):
// `--FLAG N` (lo..hi) when given, else on a resume the recorded value (`read_recorded`; absent
// records and a directory without checkpoint.json leave *value as it is).
absl::Status IntFlagOrRecorded(const ParsedArgs& args, const std::string& flag, int lo, int hi, bool resumes,
                               const std::function<absl::StatusOr<std::optional<int>>()>& read_recorded, int* value) {
  if (auto v = args.Get(flag)) {
    if (!absl::SimpleAtoi(*v, value) || *value < lo || *value > hi) {
      return absl::InvalidArgumentError(
          absl::StrCat("--", flag, " must be an integer in ", lo, "..", hi, ", not '", *v, "'"));
    }
    return absl::OkStatus();
  }
  if (!resumes) return absl::OkStatus();
  absl::StatusOr<std::optional<int>> recorded = read_recorded();
  if (!recorded.ok()) return absl::IsNotFound(recorded.status()) ? absl::OkStatus() : recorded.status();
  if (recorded->has_value()) *value = **recorded;
  return absl::OkStatus();
}

}  // namespace

int RunTrainCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(
      argv, {{"log"}, {"out"}, {"iterations"}, {"resolution-scale"}, {"holdout-every"}, {"seed"}, {"resume", false},
             {"checkpoint-every"}, {"no-sky", false}, {"exposure", false}, {"pose-refinement", false},
             {"pose-lr-scale"}, {"pose-refine-from"}, {"pose-refine-until"}, {"no-depth", false},
             {"deterministic", false}, {"backend"}, {"voxel"}, {"field"}, {"static-iterations"}, {"field-size"},
             {"lidar-weight"}, {"no-lidar-loss", false}, {"lidar-every"}, {"clip-frames"}, {"clip-overlap"},
             {"field-modules"}, {"field-decoder-max-dlog-scale"}, {"field-device"}, {"field-optimizer"},
             {"field-init"}, {"field-lambda-dx"}, {"field-lambda-dsh"}, {"field-l1-time-planes"},
             {"field-lr-scale"}, {"field-lr-decay-iterations"}, {"field-time-resolution"},
             {"position-lr-decay-iterations"}, {"field-ext-lr-scale"}, {"field-ext-lr-decay-iterations"},
             {"low-res-scale"}, {"low-res-iterations"}, {"field-motion-prior"},
             {"field-motion-prior-scans"}, {"densify-until"}});
  if (!args.ok()) return Fail(2, args.status());
  if (!args->positional().empty()) {
    return Fail(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  absl::StatusOr<std::string> log_path = args->Required("log");
  if (!log_path.ok()) return Fail(2, log_path.status());
  absl::StatusOr<std::string> out = args->Required("out");
  if (!out.ok()) return Fail(2, out.status());
  train::TrainOptions opt;
  if (auto v = args->Get("iterations"); v && (!absl::SimpleAtoi(*v, &opt.iterations) || opt.iterations < 1 ||
                                              opt.iterations > 10'000'000)) {
    return Fail(2, absl::InvalidArgumentError("--iterations must be in 1..10000000"));
  }
  if (auto v = args->Get("resolution-scale"); v && (!absl::SimpleAtod(*v, &opt.resolution_scale) ||
                                                    !(opt.resolution_scale > 0 && opt.resolution_scale <= 1))) {
    return Fail(2, absl::InvalidArgumentError("--resolution-scale must be in (0, 1]"));
  }
  // Low resolution first (docs/training.md "Low resolution first"): the first N iterations at scale S.
  // `--low-res-iterations 0` alone: none (a resume otherwise keeps the one checkpoint.json records).
  const bool no_low_res =
      !args->Has("low-res-scale") && args->Get("low-res-iterations") == std::optional<std::string>("0");
  if (!no_low_res && args->Has("low-res-scale") != args->Has("low-res-iterations")) {
    return Fail(2, absl::InvalidArgumentError(
                       "--low-res-scale and --low-res-iterations go together (--low-res-iterations 0 alone: none)"));
  }
  if (auto v = args->Get("low-res-scale")) {
    train::LowResStage low;
    const std::string n = args->Get("low-res-iterations").value_or("");
    if (!absl::SimpleAtod(*v, &low.resolution_scale) || !absl::SimpleAtoi(n, &low.iterations)) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--low-res-scale and --low-res-iterations take a number "
                                                             "and an integer, not '", *v, "' and '", n, "'")));
    }
    opt.low_res = low;
    // The stage's range rules are the trainer's (a scale below the run's, fewer iterations).
    if (absl::Status s = train::CheckLowResStage(opt); !s.ok()) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--low-res-scale / --low-res-iterations: ", s.message())));
    }
  }
  if (auto v = args->Get("holdout-every"); v && (!absl::SimpleAtoi(*v, &opt.holdout_every) || opt.holdout_every < 0 ||
                                                 opt.holdout_every == 1)) {
    return Fail(2, absl::InvalidArgumentError("--holdout-every must be 0 (none) or >= 2"));
  }
  if (auto v = args->Get("seed"); v && !absl::SimpleAtoi(*v, &opt.seed)) {
    return Fail(2, absl::InvalidArgumentError("--seed must be a non-negative integer"));
  }
  if (auto v = args->Get("checkpoint-every"); v && (!absl::SimpleAtoi(*v, &opt.checkpoint_every) ||
                                                    opt.checkpoint_every < 0)) {
    return Fail(2, absl::InvalidArgumentError("--checkpoint-every must be >= 0"));
  }
  if (auto v = args->Get("voxel"); v && (!absl::SimpleAtod(*v, &opt.init_voxel_m) || !(opt.init_voxel_m > 0))) {
    return Fail(2, absl::InvalidArgumentError("--voxel must be a positive number"));
  }
  if (auto v = args->Get("backend")) {
    absl::StatusOr<Backend> b = ParseBackend(*v);
    if (!b.ok()) return Fail(2, b.status());
    opt.backend = *b == Backend::kAuto ? Backend::kCpu : *b;
  }
  if (auto v = args->Get("field")) {
    // --field extended: S3Gaussian's stages with the seed paper's modules on its field
    // (docs/field.md "Extended field"); --field-modules picks them (default: all).
    absl::StatusOr<train::FieldMode> m = *v == "extended" ? train::FieldMode::kS3Gaussian : train::ParseFieldMode(*v);
    if (!m.ok()) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--field must be static, s3gaussian or extended, not '",
                                                             *v, "'")));
    }
    opt.field.mode = *m;
    if (*v == "extended") {
      absl::StatusOr<field::ExtendedFieldConfig> ec =
          field::ExtendedFieldConfig::WithModules(args->Get("field-modules").value_or("all"));
      if (!ec.ok()) return Fail(2, ec.status());
      opt.field.extended = *ec;
    }
  }
  bool default_field_notice = false;  // said once the log has opened (bad input stays one line)
  if (!args->Get("field")) {
    absl::StatusOr<train::FieldMode> m = DefaultFieldMode(*args, opt.iterations, opt.field.static_iterations, *out);
    if (!m.ok()) return Fail(2, m.status());
    opt.field.mode = *m;
    default_field_notice = *m == train::FieldMode::kS3Gaussian;
  }
  if (args->Get("field-modules") && !opt.field.extended) {
    return Fail(2, absl::InvalidArgumentError("--field-modules needs --field extended"));
  }
  // The bound on the decoder's Δlog-scale (docs/field.md "The decoder's Δlog-scale"; 0: unbounded,
  // as before session 13). A new fine stage takes it; a resumed one keeps its checkpoint's.
  if (auto v = args->Get("field-decoder-max-dlog-scale")) {
    if (!opt.field.extended || !opt.field.extended->decoder) {
      return Fail(2, absl::InvalidArgumentError(
                         "--field-decoder-max-dlog-scale needs --field extended with the decoder module"));
    }
    double b = 0;
    if (!absl::SimpleAtod(*v, &b) || !(b >= 0 && b <= 50)) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat(
                         "--field-decoder-max-dlog-scale must be a number in [0, 50] (0: unbounded), not '", *v, "'")));
    }
    opt.field.extended->decoder_max_dlog_scale = static_cast<float>(b);
  }
  if (auto v = args->Get("static-iterations")) {
    if (opt.field.mode != train::FieldMode::kS3Gaussian) {
      return Fail(2, absl::InvalidArgumentError("--static-iterations needs --field s3gaussian"));
    }
    if (!absl::SimpleAtoi(*v, &opt.field.static_iterations) || opt.field.static_iterations < 0 ||
        opt.field.static_iterations >= opt.iterations) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--static-iterations must be in 0..", opt.iterations - 1,
                                                             " (below --iterations, the total)")));
    }
  } else if (opt.field.mode == train::FieldMode::kS3Gaussian && opt.field.static_iterations >= opt.iterations) {
    return Fail(2, absl::InvalidArgumentError(absl::StrCat("--field s3gaussian: the static stage (",
                                                           opt.field.static_iterations,
                                                           " iterations by default) must be shorter than --iterations; "
                                                           "set --static-iterations")));
  }
  // Testing only (docs/training.md): a tiny field so that CLI tests run in seconds.
  if (auto v = args->Get("field-size")) {
    if (*v == "small") {
      opt.field.config.channels = 4;
      opt.field.config.base_resolution = 8;
      opt.field.config.multires = {1, 2};
      opt.field.config.time_resolution = 6;
      opt.field.config.width = 16;
    } else if (*v != "spec") {
      return Fail(2, absl::InvalidArgumentError("--field-size must be spec or small"));
    }
  }
  // The space-time planes' resolution along time (spec 25 cells for a 50-frame clip; docs/training.md
  // "Field time resolution").
  if (auto v = args->Get("field-time-resolution")) {
    if (!absl::SimpleAtoi(*v, &opt.field.config.time_resolution) || opt.field.config.time_resolution < 2 ||
        opt.field.config.time_resolution > 1000) {
      return Fail(2, absl::InvalidArgumentError(
                         absl::StrCat("--field-time-resolution must be an integer in 2..1000, not '", *v, "'")));
    }
  }
  // The heads' init (docs/training.md "Field init"): spec (S3Gaussian's, the default: it learns
  // motion sooner) or zero-heads (the fine stage starts exactly from the static model,
  // FieldConfig::zero_init_heads).
  opt.field.config.zero_init_heads = false;
  if (auto v = args->Get("field-init")) {
    if (*v != "spec" && *v != "zero-heads") {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--field-init must be spec or zero-heads, not '", *v, "'")));
    }
    opt.field.config.zero_init_heads = *v == "zero-heads";
  }
  // The Δ sparsity weights (S3Gaussian's lambda_dx / lambda_dshs, 1e-3 each) and the time planes'
  // L1 towards 1 (l1_time_planes, 1e-4): larger values keep more of the scene still, which the
  // server's static skip turns into serving time (docs/field.md "Motion sparsity").
  for (const auto& [flag, weight] :
       {std::pair<const char*, double*>{"field-lambda-dx", &opt.field.hyper.lambda_dx},
        std::pair<const char*, double*>{"field-lambda-dsh", &opt.field.hyper.lambda_dsh},
        std::pair<const char*, double*>{"field-l1-time-planes", &opt.field.hyper.l1_time_planes}}) {
    if (auto v = args->Get(flag); v && (!absl::SimpleAtod(*v, weight) || !(*weight >= 0 && *weight <= 100))) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--", flag, " must be a number in [0, 100], not '", *v, "'")));
    }
    if (args->Has(flag) && opt.field.mode == train::FieldMode::kStatic) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--", flag, " needs a field (a static run has none)")));
    }
  }
  // The LiDAR motion prior (docs/training.md "Motion prior"): the weight of Δx's pull towards the
  // motion of the moving objects tracked in the training frames' scans.
  if (auto v = args->Get("field-motion-prior")) {
    double w;
    if (!absl::SimpleAtod(*v, &w) || !(w >= 0 && w <= train::kMaxMotionPriorWeight)) {
      return Fail(2, absl::InvalidArgumentError(
                         absl::StrCat("--field-motion-prior must be a number in [0, 10000], not '", *v, "'")));
    }
    if (opt.field.mode == train::FieldMode::kStatic) {
      return Fail(2, absl::InvalidArgumentError("--field-motion-prior needs a field (a static run has none)"));
    }
    opt.motion_prior.weight = w;
  }
  // Which of an object's scans assign Gaussians to it (docs/training.md "Motion prior").
  if (auto v = args->Get("field-motion-prior-scans")) {
    const std::optional<bool> all_scans = train::ParseMotionPriorScans(*v);
    if (!all_scans) {
      return Fail(2, absl::InvalidArgumentError(
                         absl::StrCat("--field-motion-prior-scans must be 'last' or 'all', not '", *v, "'")));
    }
    if (opt.field.mode == train::FieldMode::kStatic) {
      return Fail(2, absl::InvalidArgumentError("--field-motion-prior-scans needs a field (a static run has none)"));
    }
    opt.motion_prior.all_scans = *all_scans;
  }
  // The field's learning rates (docs/training.md "Field learning rates"): a multiplier on both
  // groups and the length of their exponential decay (spec 30 000 fine iterations). streetsim's
  // default is 10x the spec's rates, which are set for a 50 000-iteration fine stage: on KITTI it
  // is +2.35 dB held-out after 500 fine iterations at 0.25 scale (same warm-up, A/B), and at full
  // resolution 500 fine iterations reach what the spec's rates reached after ~2000;
  // `--field-lr-scale 1` is S3Gaussian's.
  opt.field.hyper.lr_scale = kDefaultFieldLrScale;
  if (absl::Status st =
          ParseLrScheduleFlags(*args, "field-lr", &opt.field.hyper.lr_scale, &opt.field.hyper.lr_decay_steps);
      !st.ok()) {
    return Fail(2, st);
  }
  // A resume of a run that has a checkpoint: its checkpoint.json's records (field rates, low-resolution
  // stage, pose schedule, position decay) apply unless flags say otherwise.
  const bool resumes_checkpoint =
      args->Has("resume") && std::filesystem::exists(std::filesystem::path(*out) / "checkpoint.bin");
  // A resumed run keeps its own schedule unless told otherwise, value by value (annealing a run is
  // `--resume --field-lr-decay-iterations N` alone, which must not also reset its scale): the one
  // its checkpoint.json records, else the spec's where a fine stage began before the file recorded
  // it (its field trained at those rates); a run still in its static warm-up takes the default.
  if (resumes_checkpoint && opt.field.mode != train::FieldMode::kStatic &&
      !(args->Has("field-lr-scale") && args->Has("field-lr-decay-iterations"))) {
    absl::StatusOr<std::optional<train::FieldLrSchedule>> recorded = train::ReadCheckpointFieldLr(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    const train::FieldCheckpointsFound found = train::FindFieldCheckpoints(*out);
    std::optional<train::FieldLrSchedule> own = recorded.ok() ? *recorded : std::nullopt;
    if (!own && (found.base || found.extended)) {
      // Runs between the flag and checkpoint.json's record of it have the schedule only in their
      // train_meta.json, written when a segment ended at the checkpoint's iteration.
      absl::StatusOr<std::optional<train::FieldLrSchedule>> meta = train::ReadTrainMetaFieldLr(*out);
      if (!meta.ok()) return Fail(2, meta.status());
      own = meta->value_or(train::FieldLrSchedule{});  // else the spec's, the only one then
    }
    if (own) {
      KeepRecordedLrSchedule(*args, "field-lr", *own, &opt.field.hyper.lr_scale, &opt.field.hyper.lr_decay_steps);
    }
  }
  // A resumed run keeps its low-resolution stage too, unless told (checkpoint.json records it).
  if (resumes_checkpoint && !args->Has("low-res-iterations")) {
    absl::StatusOr<std::optional<train::LowResStage>> recorded = train::ReadCheckpointLowResStage(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && recorded->has_value()) {
      opt.low_res = **recorded;
      if (absl::Status s = train::CheckLowResStage(opt); !s.ok()) {
        return Fail(2, absl::InvalidArgumentError(absl::StrCat(
                           *out, " was trained with a low-resolution stage that does not fit these flags: ",
                           s.message(), " (--low-res-iterations 0: none)")));
      }
    }
  }
  // ... and its motion prior (a segmented run must not drop it on the resume that forgets the flag;
  // `--field-motion-prior 0` turns it off).
  if (resumes_checkpoint && opt.field.mode != train::FieldMode::kStatic && !args->Has("field-motion-prior")) {
    absl::StatusOr<std::optional<double>> recorded = train::ReadCheckpointMotionPrior(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && recorded->has_value()) opt.motion_prior.weight = **recorded;
  }
  if (resumes_checkpoint && opt.field.mode != train::FieldMode::kStatic && !args->Has("field-motion-prior-scans")) {
    absl::StatusOr<std::optional<bool>> recorded = train::ReadCheckpointMotionPriorAllScans(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && recorded->has_value()) opt.motion_prior.all_scans = **recorded;
  }
  for (const char* flag : {"field-lr-scale", "field-lr-decay-iterations", "field-time-resolution"}) {
    if (args->Has(flag) && opt.field.mode == train::FieldMode::kStatic) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--", flag, " needs a field (a static run has none)")));
    }
  }
  // Where S3Gaussian's field runs (auto: Vulkan with --backend vulkan on a GPU, else the cpu).
  if (auto v = args->Get("field-device")) {
    absl::StatusOr<train::FieldDevice> d = train::ParseFieldDevice(*v);
    if (!d.ok()) return Fail(2, d.status());
    opt.field.device = *d;
  }
  // Where a Vulkan field's regularisers and Adam run (auto: the device on a GPU, the host on a CPU
  // Vulkan device; docs/field.md "The optimiser on the device").
  if (auto v = args->Get("field-optimizer")) {
    absl::StatusOr<train::FieldOptimizerPlace> place = train::ParseFieldOptimizerPlace(*v);
    if (!place.ok()) return Fail(2, place.status());
    opt.field.optimizer = *place;
  }
  opt.resume = args->Has("resume");
  opt.sky = !args->Has("no-sky");
  opt.exposure = args->Has("exposure");
  opt.pose_refinement = args->Has("pose-refinement");
  bool pose_schedule_recorded = false;
  // A resumed run that refines its poses keeps its own schedule, value by value, unless told: a
  // `--pose-refine-until` dropped on one resume would otherwise set its frozen corrections moving.
  if (resumes_checkpoint) {
    absl::StatusOr<std::optional<train::PoseRefinementSchedule>> recorded = train::ReadCheckpointPoseRefinement(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && recorded->has_value()) {
      const train::PoseRefinementSchedule& own = **recorded;
      pose_schedule_recorded = true;
      opt.pose_refinement = true;
      if (!args->Has("pose-lr-scale")) {  // given, it scales the defaults, as on a new run
        opt.hyper.pose_rotation_lr = own.rotation_lr;
        opt.hyper.pose_translation_lr = own.translation_lr;
      }
      opt.hyper.pose_refine_from = own.from;
      opt.hyper.pose_refine_until = own.until;
    }
  }
  if (auto v = args->Get("pose-lr-scale")) {
    double scale = 0;
    if (!opt.pose_refinement) return Fail(2, absl::InvalidArgumentError("--pose-lr-scale needs --pose-refinement"));
    if (!absl::SimpleAtod(*v, &scale) || !(scale > 0 && scale <= 1000)) {
      return Fail(2, absl::InvalidArgumentError("--pose-lr-scale must be a number in (0, 1000]"));
    }
    opt.hyper.pose_rotation_lr *= scale;
    opt.hyper.pose_translation_lr *= scale;
  }
  if (auto v = args->Get("pose-refine-from")) {
    if (!opt.pose_refinement) return Fail(2, absl::InvalidArgumentError("--pose-refine-from needs --pose-refinement"));
    if (!absl::SimpleAtoi(*v, &opt.hyper.pose_refine_from) || opt.hyper.pose_refine_from < 0) {
      return Fail(2, absl::InvalidArgumentError("--pose-refine-from must be an integer >= 0"));
    }
  }
  if (auto v = args->Get("pose-refine-until")) {
    if (!opt.pose_refinement) return Fail(2, absl::InvalidArgumentError("--pose-refine-until needs --pose-refinement"));
    if (!absl::SimpleAtoi(*v, &opt.hyper.pose_refine_until) || opt.hyper.pose_refine_until < 1) {
      return Fail(2, absl::InvalidArgumentError("--pose-refine-until must be an integer >= 1"));
    }
  }
  // A field run refines its poses on the static model and keeps them for the fine stage: kept
  // moving there, the corrections compete with the time-dependent field for the same misalignment
  // (KITTI, full resolution: frozen +0.5..+1.2 dB held-out over the log's poses, refined throughout
  // 0.5 dB behind them; docs/benchmarks.md "Camera pose refinement").
  // Where the static stage is too short to refine in, the corrections move throughout.
  if (opt.pose_refinement && opt.field.mode != train::FieldMode::kStatic && !args->Has("pose-refine-until") &&
      !pose_schedule_recorded && opt.field.static_iterations > opt.hyper.pose_refine_from) {
    opt.hyper.pose_refine_until = opt.field.static_iterations;
  }
  // The Gaussian means' rate decays over 30 000 iterations of a stage (3DGS's, set for a 30 000-
  // iteration run); a shorter decay anneals them, as --field-lr-decay-iterations does the field's.
  // A resume keeps its recorded one unless told.
  if (absl::Status s = IntFlagOrRecorded(
          *args, "position-lr-decay-iterations", 1, 10'000'000, resumes_checkpoint,
          [&] { return train::ReadCheckpointPositionLrDecay(*out); }, &opt.hyper.lr_decay_steps);
      !s.ok()) {
    return Fail(2, s);
  }
  // Densification (and the opacity reset with it) runs until this stage iteration: 3DGS stops at
  // 15 000 of 30 000 and polishes a fixed set of Gaussians; `--resume --densify-until N` ends a
  // trained run's. A resume keeps its recorded one unless told.
  if (absl::Status s = IntFlagOrRecorded(
          *args, "densify-until", 0, train::kMaxDensifyUntil, resumes_checkpoint,
          [&] { return train::ReadCheckpointDensifyUntil(*out); }, &opt.hyper.densify_until);
      !s.ok()) {
    return Fail(2, s);
  }
  // The extension's network rate (ExtHyper: the paper's 1.6e-3 -> 1.6e-4 over 30 000 fine
  // iterations) has its own switches: the base field's flags leave it alone, so that modules
  // grown on an annealed field can be annealed with it (docs/training.md "Growing modules on a
  // trained field"). A resumed extended run keeps its recorded schedule, value by value.
  if (absl::Status st = ParseLrScheduleFlags(*args, "field-ext-lr", &opt.field.ext_hyper.lr_scale,
                                             &opt.field.ext_hyper.lr_decay_steps);
      !st.ok()) {
    return Fail(2, st);
  }
  for (const char* flag : {"field-ext-lr-scale", "field-ext-lr-decay-iterations"}) {
    if (args->Has(flag) && !opt.field.extended) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--", flag, " needs --field extended")));
    }
  }
  if (resumes_checkpoint && opt.field.extended &&
      !(args->Has("field-ext-lr-scale") && args->Has("field-ext-lr-decay-iterations"))) {
    absl::StatusOr<std::optional<train::FieldLrSchedule>> recorded = train::ReadCheckpointExtLr(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && recorded->has_value()) {
      KeepRecordedLrSchedule(*args, "field-ext-lr", **recorded, &opt.field.ext_hyper.lr_scale,
                             &opt.field.ext_hyper.lr_decay_steps);
    }
  }
  // --field extended on a resume: an S3Gaussian run's checkpoint grows the modules (they join at
  // their init, leaving its renders as they were; docs/training.md "Growing modules on a trained
  // field"); an extended run's records where its modules joined.
  if (resumes_checkpoint && opt.field.extended) {
    absl::StatusOr<std::string> recorded = train::ReadCheckpointField(*out);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return Fail(2, recorded.status());
    if (recorded.ok() && *recorded == "s3gaussian") {
      opt.field.grow_extension = true;
    } else if (recorded.ok() && *recorded == "extended") {
      absl::StatusOr<int64_t> from = train::ReadCheckpointExtensionFrom(*out);
      if (!from.ok()) return Fail(2, from.status());
      opt.field.extension_from_fine_iteration = *from;
    }
  }
  opt.depth_loss = !args->Has("no-depth");
  opt.deterministic = args->Has("deterministic");
  // LiDAR losses (docs/training.md "LiDAR losses").
  if (auto v = args->Get("lidar-weight"); v && (!absl::SimpleAtod(*v, &opt.lidar_weight) ||
                                                !(opt.lidar_weight >= 0 && opt.lidar_weight <= 1e6))) {
    return Fail(2, absl::InvalidArgumentError("--lidar-weight must be a number in 0..1e6"));
  }
  if (auto v = args->Get("lidar-every"); v && (!absl::SimpleAtoi(*v, &opt.lidar_every) || opt.lidar_every < 1)) {
    return Fail(2, absl::InvalidArgumentError("--lidar-every must be an integer >= 1"));
  }
  if (args->Has("no-lidar-loss")) {
    if (args->Get("lidar-weight")) {
      return Fail(2, absl::InvalidArgumentError("--no-lidar-loss and --lidar-weight contradict each other"));
    }
    opt.lidar_weight = 0;
  }

  // Clips (docs/training.md "Clips"): 0 = one clip over the whole log; S3Gaussian uses 50.
  train::ClipTrainOptions clip_opt;
  if (auto v = args->Get("clip-frames"); v && !absl::SimpleAtoi(*v, &clip_opt.clip_frames)) {
    return Fail(2, absl::InvalidArgumentError(absl::StrCat("--clip-frames must be an integer, not '", *v, "'")));
  }
  if (absl::Status s = train::PlanClips(1, clip_opt.clip_frames).status(); !s.ok()) return Fail(2, s);
  // Each clip also trains on K frames of each neighbour, so a switch falls between fitted frames
  // (without the flag: the set's own K on --resume, else a tenth of a clip; TrainClips decides).
  if (auto v = args->Get("clip-overlap")) {
    int overlap = 0;
    if (!absl::SimpleAtoi(*v, &overlap)) {
      return Fail(2, absl::InvalidArgumentError(absl::StrCat("--clip-overlap must be an integer, not '", *v, "'")));
    }
    if (clip_opt.clip_frames == 0) return Fail(2, absl::InvalidArgumentError("--clip-overlap needs --clip-frames N"));
    if (absl::Status s = train::CheckClipOverlap(clip_opt.clip_frames, overlap); !s.ok()) return Fail(2, s);
    clip_opt.overlap_frames = overlap;
  }

  // One writer per directory, held to the end. A server's trainer waits for its predecessor: after
  // a server restart the previous trainer of the same job may still be writing its last checkpoint.
  absl::StatusOr<train::RunDirLock> lock = train::RunDirLock::Acquire(*out, StartedByServer() ? 180 : 0);
  if (!lock.ok()) return Fail(2, lock.status());
  absl::StatusOr<DriveLog> log = OpenLog(*log_path);
  if (!log.ok()) return Fail(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  if (default_field_notice) {
    std::fprintf(stderr, "streetsim train: --field s3gaussian (the default for runs with a fine stage; "
                         "--field static for a static model)\n");
  }
  if (opt.field.extended && log->frames.size() >= 2) {
    // The token window's Δ: one frame (the median interval of the log's frames).
    std::vector<int64_t> dt;
    for (size_t i = 1; i < log->frames.size(); ++i) dt.push_back(log->frames[i].time_us - log->frames[i - 1].time_us);
    std::nth_element(dt.begin(), dt.begin() + dt.size() / 2, dt.end());
    opt.field.frame_interval_us = std::max<int64_t>(0, dt[dt.size() / 2]);
  }
  const bool tty = isatty(fileno(stderr));
  auto progress = [&](const train::Progress& p) {
    const int width = 30;
    const int filled = static_cast<int>(width * p.iteration / std::max<int64_t>(1, p.total));
    std::string bar(filled, '#');
    bar.resize(width, '.');
    std::fprintf(stderr, "%s[%s] %lld/%lld  loss %.4f  psnr %.2f dB  %zu Gaussians  %.2f it/s  ETA %s%s%s",
                 tty ? "\r" : "", bar.c_str(), static_cast<long long>(p.iteration), static_cast<long long>(p.total),
                 p.loss, p.psnr, p.gaussians, p.it_per_s, Duration(p.eta_s).c_str(),
                 p.low_res_scale > 0
                     ? absl::StrCat(" (low-resolution stage at scale ", p.low_res_scale, ")").c_str()
                 : p.eta_static_stage_only ? " (static stage; the fine stage is slower)"
                                           : "",
                 tty ? "" : "\n");
    std::fflush(stderr);
  };
  opt.stop_requested = &g_stop_requested;
  InstallStopHandlers();
  absl::StatusOr<train::ClipTrainResult> clips = train::TrainClips(*log, *out, opt, clip_opt, progress);
  if (tty) std::fprintf(stderr, "\n");
  absl::StatusOr<train::TrainResult> r =
      !clips.ok() ? absl::StatusOr<train::TrainResult>(clips.status())
                  : clips->runs.empty() ? train::TrainResult{} : clips->runs.back().result;
  if (!r.ok() && absl::IsCancelled(r.status()) && g_stop_signal != 0) {
    return Fail(128 + g_stop_signal, r.status());  // 130 for SIGINT, 143 for SIGTERM, as a killed run
  }
  if (!r.ok()) {
    const absl::StatusCode c = r.status().code();
    return Fail(c == absl::StatusCode::kInvalidArgument || c == absl::StatusCode::kNotFound ||
                        c == absl::StatusCode::kDataLoss || c == absl::StatusCode::kFailedPrecondition
                    ? 2 : 1,
                r.status());
  }
  // The log's rig, time range and trajectory beside the scene, for `streetsim serve`.
  const std::filesystem::path out_dir(*out);
  if (absl::Status s = WriteSceneManifest(*log, std::filesystem::absolute(out_dir).filename().string(),
                                          (out_dir / "scene.json").string());
      !s.ok()) {
    return Fail(1, s);
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
