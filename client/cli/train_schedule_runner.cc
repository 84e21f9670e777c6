#include "client/cli/train_schedule_runner.h"

#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <set>

#include "absl/strings/cord.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "scene/train/checkpoint_run.h"
#include "scene/train/config/train_settings.h"
#include "scene/train/stage_history.h"
#include "scene/train/train_state.h"

namespace streetsim {
namespace {

// The trainer's options for one segment of the run (a schedule's stage; run_config.h).
absl::StatusOr<train::config::TrainRunOptions> SegmentOptions(const train::config::Segment& segment,
                                                             const std::string& out_dir, const DriveLog& log) {
  absl::StatusOr<train::config::TrainRunOptions> o = train::config::ResolveTrainOptions(segment.settings, segment.end);
  if (!o.ok()) return o.status();
  train::TrainOptions& opt = o->train;
  // The motion prior tracks objects in the scans: a preset's prior on a camera-only log is left
  // out (the run says so once); one the user asked for is an error.
  if (opt.motion_prior.weight > 0 && log.lidars.empty()) {
    if (segment.settings.given("field-motion-prior")) {
      return absl::InvalidArgumentError("field-motion-prior needs the log's LiDAR, and this log has none");
    }
    opt.motion_prior.weight = 0;
  }
  opt.motion_prior.optional = !segment.settings.given("field-motion-prior");
  if (opt.field.extended && log.frames.size() >= 2) {
    // The token window's Δ: one frame (the median interval of the log's frames).
    std::vector<int64_t> dt;
    for (size_t i = 1; i < log.frames.size(); ++i) dt.push_back(log.frames[i].time_us - log.frames[i - 1].time_us);
    std::nth_element(dt.begin(), dt.begin() + dt.size() / 2, dt.end());
    opt.field.frame_interval_us = std::max<int64_t>(0, dt[dt.size() / 2]);
  }
  // An extended stage after an S3Gaussian checkpoint grows its modules on the trained field (they
  // join at their init; docs/training.md "Growing modules on a trained field"); an extended
  // checkpoint records where they joined. Checkpoint state, not settings: checkpoint.json has it.
  if (opt.field.extended && std::filesystem::exists(std::filesystem::path(out_dir) / "checkpoint.bin")) {
    absl::StatusOr<std::string> recorded = train::ReadCheckpointField(out_dir);
    if (!recorded.ok() && !absl::IsNotFound(recorded.status())) return recorded.status();
    if (recorded.ok() && *recorded == "s3gaussian") {
      opt.field.grow_extension = true;
    } else if (recorded.ok() && *recorded == "extended") {
      absl::StatusOr<int64_t> from = train::ReadCheckpointExtensionFrom(out_dir);
      if (!from.ok()) return from.status();
      opt.field.extension_from_fine_iteration = *from;
    }
  }
  return o;
}

// The divergence guard's way out (docs/training.md "Divergence guard"): a fine stage that diverged
// goes back to its last checkpoint (from before the divergence) with the rates that were moving
// divided by 4 (the field's, and the pose corrections' where they were still moving), at most
// kMaxRollbacks times; recorded in config.json's schedule and notes. Returns the note to print, or
// the status to stop with (`diverged` itself when it is not a divergence).
constexpr int kMaxRollbacks = 2;
constexpr double kRollbackRateDivisor = 4;

absl::StatusOr<std::string> RollBack(const absl::Status& diverged, const train::config::Settings& settings,
                                     const std::string& out_dir, int rollbacks, train::config::RunConfig* config,
                                     int64_t* from) {
  const auto at_text = diverged.GetPayload(train::kDivergedAtPayload);  // absl::optional<absl::Cord>
  int64_t at = 0;
  if (!absl::IsAborted(diverged) || !at_text || !absl::SimpleAtoi(std::string(*at_text), &at)) return diverged;
  const bool fine = settings.GetText("field") != "static" && at > settings.GetInt("static-iterations");
  const double scale = settings.GetDouble("field-lr-scale");
  if (!fine) {
    return absl::AbortedError(absl::StrCat(diverged.message(), ". The guard lowers the field's rates only; the static "
                                           "stage stops here (see the log; --resume goes on from the checkpoint)"));
  }
  if (rollbacks >= kMaxRollbacks) {
    return absl::AbortedError(absl::StrCat(diverged.message(), ", after ", rollbacks,
                                           " rollbacks that lowered the rates (field-lr-scale now ", scale,
                                           "): stopping; --resume --set NAME=VALUE goes on from the checkpoint"));
  }
  absl::StatusOr<int64_t> checkpoint =
      train::PeekCheckpointIteration((std::filesystem::path(out_dir) / "checkpoint.bin").string());
  if (!checkpoint.ok()) return diverged;
  std::vector<std::string> names = {"field-lr-scale"};
  const int64_t pose_until = settings.GetInt("pose-refine-until") >= 0 ? settings.GetInt("pose-refine-until")
                                                                       : settings.GetInt("static-iterations");
  if (settings.GetBool("pose-refinement") && at > settings.GetInt("pose-refine-from") &&
      (pose_until == 0 || at <= pose_until)) {
    names.push_back("pose-lr-scale");
  }
  train::config::Settings lowered = settings;
  std::string what;
  for (const std::string& name : names) {
    const double was = settings.GetDouble(name);
    if (!lowered.Set(name, was / kRollbackRateDivisor, train::config::Origin::kGiven, "divergence guard").ok()) {
      return diverged;
    }
    absl::StrAppend(&what, what.empty() ? "" : ", ", name, " ", was, " -> ", was / kRollbackRateDivisor);
  }
  absl::StatusOr<std::vector<std::string>> changed =
      train::config::ChangeFrom(*checkpoint, lowered, std::set<std::string>(names.begin(), names.end()), config);
  if (!changed.ok()) return changed.status();
  const std::string note = absl::StrCat(
      "iteration ", at, ": the training diverged; rolled back to the checkpoint of iteration ", *checkpoint, " with ", what);
  config->notes.push_back(note);
  if (absl::Status s = train::config::WriteRunConfig(out_dir, *config); !s.ok()) return s;
  *from = *checkpoint;
  return note;
}

}  // namespace

absl::StatusOr<train::ClipTrainResult> RunSchedule(const DriveLog& log, const std::string& out_dir,
                                                   const std::atomic<bool>* stop_requested,
                                                   const std::function<void(const train::Progress&)>& progress,
                                                   train::config::ResolvedRun* run) {
  // A new run records its config at once. A resume's changes are recorded once the trainer has
  // taken them (its first progress, or its end): a change it refuses (say, another clip plan)
  // must not become the run's config.
  bool config_pending = run->resumes && (!run->changed.empty() || run->migrated);
  if (!run->resumes) {
    if (absl::Status s = train::config::WriteRunConfig(out_dir, run->config); !s.ok()) return s;
  }
  auto record_config = [&] {
    if (!config_pending) return absl::OkStatus();
    config_pending = false;
    return train::config::WriteRunConfig(out_dir, run->config);
  };
  auto on_progress = [&](const train::Progress& p) {
    if (absl::Status s = record_config(); !s.ok()) {
      std::fprintf(stderr, "streetsim train: cannot record the config: %s\n", std::string(s.message()).c_str());
    }
    if (progress) progress(p);
  };
  const bool tty = isatty(fileno(stderr));
  std::vector<train::config::Segment> segments = train::config::Segments(run->config);
  absl::StatusOr<train::ClipTrainResult> clips;
  bool resumes = run->resumes;
  int64_t done = run->done_iterations;
  int rollbacks = 0;
  for (size_t k = 0; k < segments.size();) {
    const train::config::Segment& segment = segments[k];
    if (segment.end <= done && k + 1 < segments.size()) {  // done before the resume
      ++k;
      continue;
    }
    absl::StatusOr<train::config::TrainRunOptions> o = SegmentOptions(segment, out_dir, log);
    if (!o.ok()) return o.status();
    o->train.stop_requested = stop_requested;
    // The first segment run by this process continues only a resumed run; each later one goes on
    // from the checkpoint its predecessor wrote.
    o->train.resume = resumes;
    clips = train::TrainClips(log, out_dir, o->train, o->clips, on_progress);
    if (tty) std::fprintf(stderr, "\n");
    if (!clips.ok()) {
      int64_t from = 0;
      absl::StatusOr<std::string> note = RollBack(clips.status(), segment.settings, out_dir, rollbacks, &run->config, &from);
      if (!note.ok()) return note.status();
      std::fprintf(stderr, "streetsim train: %s\nstreetsim train: %s\n", std::string(clips.status().message()).c_str(),
                   note->c_str());
      ++rollbacks;
      config_pending = false;  // RollBack wrote config.json with the change
      segments = train::config::Segments(run->config);
      done = from;
      resumes = true;
      k = 0;
      continue;
    }
    const train::TrainResult& r = clips->runs.empty() ? train::TrainResult{} : clips->runs.back().result;
    if (segments.size() > 1 && !r.heldout.frames.empty()) {
      std::fprintf(stderr, "streetsim train: stage %zu of %zu ends at iteration %lld: held-out PSNR %.2f dB\n", k + 1,
                   segments.size(), static_cast<long long>(segment.end), r.heldout.mean.psnr);
      // The run's PSNR-versus-time curve (DIR/heldout_history.json, heldout_curve.png).
      if (absl::Status s = train::AppendStagePoint(out_dir, segment.end, r.seconds, r.heldout.mean.psnr,
                                                   r.heldout.mean.ssim);
          !s.ok()) {
        std::fprintf(stderr, "streetsim train: cannot record the stage's figures: %s\n",
                     std::string(s.message()).c_str());
      }
    }
    resumes = true;
    done = segment.end;
    ++k;
  }
  if (clips.ok()) {
    if (absl::Status s = record_config(); !s.ok()) return s;
  }
  return clips;
}

}  // namespace streetsim
