#include "scene/train/clip_training.h"

#include <filesystem>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/train/resolution_schedule.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/field_io.h"
#include "scene/log/scene_manifest.h"
#include "scene/train/dynamic_pixels.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;

// The same time mapping, sizes and layout: a prior of another --field-size cannot seed this field.
bool SameFieldConfig(const field::FieldConfig& a, const field::FieldConfig& b) {
  return a.channels == b.channels && a.base_resolution == b.base_resolution && a.multires == b.multires &&
         a.time_resolution == b.time_resolution && a.width == b.width && a.full_time_range == b.full_time_range;
}

absl::Status SamePlan(const ClipSet& on_disk, const ClipSet& planned, const std::string& dir) {
  bool same = on_disk.clip_frames == planned.clip_frames && on_disk.overlap_frames == planned.overlap_frames &&
              on_disk.num_frames == planned.num_frames && on_disk.clips.size() == planned.clips.size();
  // The trained frames follow from the frames, the overlap and the log's length.
  for (size_t k = 0; same && k < planned.clips.size(); ++k) same = on_disk.clips[k].frames == planned.clips[k].frames;
  if (same) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      dir, " holds clips of ", on_disk.clip_frames, " frames (overlap ", on_disk.overlap_frames, ") over a ",
      on_disk.num_frames, "-frame log; this run plans ", planned.clip_frames, " (overlap ", planned.overlap_frames,
      ") over ", planned.num_frames,
      " (resume with the same --clip-frames, --clip-overlap and log, or train into another directory)"));
}

}  // namespace

namespace {

// One clip at one resolution (opt.resolution_scale); TrainClip runs it once per resolution stage.
absl::StatusOr<TrainResult> TrainClipAtScale(const DriveLog& log, const ClipRange& frames, const std::string& dir,
                                             const TrainOptions& opt,
                                             const std::function<void(const Progress&)>& progress) {
  if (frames.first_frame < 0 || frames.end_frame > static_cast<int>(log.frames.size()) || frames.size() < 1) {
    return absl::InvalidArgumentError(absl::StrCat("clip frames [", frames.first_frame, ", ", frames.end_frame,
                                                   ") are not inside the log's ", log.frames.size()));
  }
  const DriveLog sub = ClipLog(log, frames);
  // Every view of the clip, then the log-wide hold-out rule on the log's frame index (a clip
  // starting at frame 50 holds out 51, 55, ... as the whole-log run does).
  DatasetOptions dopt;
  dopt.grayscale = opt.grayscale_cameras;
  dopt.resolution_scale = opt.resolution_scale;
  dopt.holdout_every = 0;
  dopt.split = Split::kAll;
  const bool want_test = opt.write_outputs && opt.holdout_every > 0;
  dopt.load_depth = opt.depth_loss || want_test;
  absl::StatusOr<std::vector<View>> all = LoadViews(sub, dopt);
  if (!all.ok()) return all.status();
  std::vector<View> train, test;
  for (View& v : *all) {
    v.frame += frames.first_frame;
    if (!IsHeldOut(v.frame, opt.holdout_every)) {
      if (!opt.depth_loss) v.lidar.clear();
      train.push_back(std::move(v));
    } else if (want_test) {
      test.push_back(std::move(v));
    }
  }
  if (train.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("clip of frames [", frames.first_frame, ", ", frames.end_frame,
                                                   ") has no training views"));
  }
  // PSNR* masks read the log's scans around each held-out frame (never trained on).
  if (absl::Status s = AttachDynamicPixels(log, &test); !s.ok()) return s;
  TrainOptions copt = opt;
  if (copt.lidar_log == nullptr) copt.lidar_log = &log;  // View::frame indexes the whole log
  std::optional<GaussianStore> init;
  if (!(opt.resume && fs::exists(fs::path(dir) / "checkpoint.bin"))) {
    // New Gaussians from the clip's training frames only (spec 8: clip 2 from frames 50-99).
    absl::StatusOr<GaussianStore> built = BuildTrainingInitialScene(log, frames.first_frame, frames.end_frame, opt);
    if (!built.ok()) return built.status();
    init = std::move(*built);
  }
  absl::StatusOr<TrainResult> r = TrainOnViews(train, init ? &*init : nullptr, test, dir, copt, progress);
  if (!r.ok()) return r.status();
  if (r->iterations >= opt.iterations && opt.write_outputs) {
    // The clip's rig, time range and trajectory: each clip is a scene `streetsim serve` can load.
    const std::string name = absl::StrCat(fs::absolute(dir).parent_path().filename().string(), "/",
                                          fs::path(dir).filename().string());
    if (absl::Status s = WriteSceneManifest(sub, name, (fs::path(dir) / "scene.json").string()); !s.ok()) return s;
  }
  return r;
}

}  // namespace

absl::StatusOr<TrainResult> TrainClip(const DriveLog& log, const ClipRange& frames, const std::string& dir,
                                      const TrainOptions& opt, const std::function<void(const Progress&)>& progress) {
  return TrainInResolutionStages(
      opt, dir, progress, [&](const TrainOptions& stage, const std::function<void(const Progress&)>& stage_progress) {
        return TrainClipAtScale(log, frames, dir, stage, stage_progress);
      });
}

absl::StatusOr<ClipTrainResult> TrainClips(const DriveLog& log, const std::string& out_dir, const TrainOptions& opt,
                                           const ClipTrainOptions& copt,
                                           const std::function<void(const Progress&)>& progress) {
  absl::StatusOr<std::vector<ClipRange>> plan = PlanClips(static_cast<int>(log.frames.size()), copt.clip_frames);
  if (!plan.ok()) return plan.status();
  if (copt.overlap_frames) {
    if (absl::Status s = CheckClipOverlap(copt.clip_frames, *copt.overlap_frames); !s.ok()) return s;
  }
  ClipTrainResult out;
  std::error_code ec;
  const fs::path manifest = fs::path(out_dir) / kClipManifestName;
  if (plan->size() == 1) {
    if (fs::exists(manifest, ec)) {
      if (opt.resume) {
        return absl::FailedPreconditionError(absl::StrCat(out_dir, " holds a clip set (", kClipManifestName,
                                                          "); resume it with its --clip-frames"));
      }
      fs::remove(manifest, ec);  // a plain scene now; consumers would otherwise read the old clips
    }
    absl::StatusOr<TrainResult> r = Train(log, out_dir, opt, progress);
    if (!r.ok()) return r.status();
    out.stopped = opt.stop_after > 0 && r->iterations < opt.iterations;
    out.runs.push_back({0, plan->front(), plan->front(), out_dir, std::move(*r)});
    return out;
  }

  std::optional<ClipSet> on_disk;
  if (opt.resume) {
    absl::StatusOr<std::optional<ClipSet>> read = ReadClipSet(out_dir);
    if (!read.ok()) return read.status();
    on_disk = std::move(*read);
  }
  // Unless given, a resume keeps the set's own overlap (a set trained before overlaps existed has
  // none); a new set gets the default.
  const int overlap = copt.overlap_frames ? *copt.overlap_frames
                      : on_disk           ? on_disk->overlap_frames
                                          : DefaultClipOverlap(copt.clip_frames);
  ClipSet set = MakeClipSet(log, copt.clip_frames, *plan, overlap);
  if (opt.resume) {
    if (on_disk) {
      if (absl::Status s = SamePlan(*on_disk, set, out_dir); !s.ok()) return s;
      for (size_t k = 0; k < set.clips.size(); ++k) set.clips[k].done = on_disk->clips[k].done;
    } else if (fs::exists(fs::path(out_dir) / "checkpoint.bin", ec)) {
      return absl::FailedPreconditionError(
          absl::StrCat(out_dir, " holds a single-scene run; resume it without --clip-frames"));
    }
  }
  fs::create_directories(out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", out_dir, ": ", ec.message()));
  if (absl::Status s = WriteClipSet(set, out_dir); !s.ok()) return s;
  out.set = set;

  for (size_t k = 0; k < set.clips.size(); ++k) {
    ClipEntry& clip = set.clips[k];
    const ClipRange trained = set.trained(k);
    const std::string dir = (fs::path(out_dir) / clip.dir).string();
    if (clip.done) {
      LOG(INFO) << "clip " << k << " (" << clip.dir << ") is done; not retrained";
      continue;
    }
    TrainOptions o = opt;
    o.seed = opt.seed + k;  // each clip its own random streams (view order, init, a fresh field)
    // The field's time axis spans the frames the clip trains on (held-out ones included).
    o.field.time_range = {log.frames[trained.first_frame].time_us, log.frames[trained.end_frame - 1].time_us};
    if (copt.stop_in_clip >= 0 && static_cast<int>(k) != copt.stop_in_clip) o.stop_after = 0;
    if (o.field.mode == FieldMode::kS3Gaussian && k > 0) {
      const std::string prior_path = (fs::path(out_dir) / set.clips[k - 1].dir / field::kFieldFileName).string();
      if (!fs::exists(prior_path, ec)) {
        return absl::FailedPreconditionError(absl::StrCat(
            prior_path, " is missing: clip ", k - 1, " was not trained with --field s3gaussian"));
      }
      absl::StatusOr<field::DeformationField> prior = field::LoadField(prior_path);
      if (!prior.ok()) return prior.status();
      if (!SameFieldConfig(prior->config(), o.field.config)) {
        return absl::FailedPreconditionError(
            absl::StrCat(prior_path, ": the field has another configuration (was --field-size changed?)"));
      }
      if (o.field.extended) {
        // --field extended: the extension chains too (field_ext.bin, tied to field.bin by its checksum).
        const std::string ext_path =
            (fs::path(out_dir) / set.clips[k - 1].dir / field::kExtendedFieldFileName).string();
        if (!fs::exists(ext_path, ec)) {
          return absl::FailedPreconditionError(
              absl::StrCat(ext_path, " is missing: clip ", k - 1, " was not trained with --field extended"));
        }
        absl::StatusOr<field::ExtendedField> ext = field::LoadExtendedField(ext_path, *prior);
        if (!ext.ok()) return ext.status();
        o.field.ext_prior = std::make_shared<const field::ExtendedField>(std::move(*ext));
      }
      o.field.prior = std::make_shared<const field::DeformationField>(std::move(*prior));
    }
    LOG(INFO) << "clip " << k << " of " << set.clips.size() << ": frames [" << clip.frames.first_frame << ", "
              << clip.frames.end_frame << "), trained on [" << trained.first_frame << ", "
              << trained.end_frame << ") -> " << dir
              << (o.field.prior ? (o.field.ext_prior ? " (fine stage from the previous clip's field and extension)"
                                                     : " (fine stage from the previous clip's field)")
                                : "");
    absl::StatusOr<TrainResult> r = TrainClip(log, trained, dir, o, progress);
    if (!r.ok()) return absl::Status(r.status().code(), absl::StrCat("clip ", k, ": ", r.status().message()));
    const bool finished = r->iterations >= opt.iterations;
    out.runs.push_back({static_cast<int>(k), clip.frames, trained, dir, std::move(*r)});
    if (!finished) {
      out.stopped = true;
      return out;
    }
    clip.done = true;
    if (absl::Status s = WriteClipSet(set, out_dir); !s.ok()) return s;
    out.set = set;
  }
  return out;
}

}  // namespace streetsim::train
