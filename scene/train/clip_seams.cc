#include "scene/train/clip_seams.h"

#include <filesystem>
#include <memory>

#include "absl/strings/str_cat.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/losses.h"
#include "scene/train/trainer.h"

namespace streetsim::train {
namespace {

// A clip scene loaded as `streetsim eval` loads it: scene.ply, field.bin if any, its sky.
struct LoadedClip {
  SceneMeta meta;
  SceneForView scene_for_view;
};

absl::StatusOr<LoadedClip> LoadClip(Engine& engine, const std::string& set_dir, const ClipEntry& clip) {
  absl::StatusOr<std::string> dir = ClipPath(set_dir, clip);
  if (!dir.ok()) return dir.status();
  absl::StatusOr<SceneMeta> meta = ReadSceneMeta(*dir);
  if (!meta.ok()) return meta.status();
  absl::StatusOr<GaussianStore> store = ReadGaussianPly((std::filesystem::path(*dir) / "scene.ply").string());
  if (!store.ok()) return store.status();
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> f = LoadSceneField(*dir);
  if (!f.ok()) return f.status();
  absl::StatusOr<SceneForView> sv = MakeSceneForView(engine, *store, *f);
  if (!sv.ok()) return sv.status();
  return LoadedClip{*meta, std::move(*sv)};
}

// The scene's renders of `views`, clamped to [0, 1] as evaluation measures them, and their mean PSNR.
absl::StatusOr<std::vector<std::vector<float>>> RenderViews(Engine& engine, const SceneForView& scene,
                                                            const Eigen::Vector3f& background,
                                                            const std::vector<View>& views, double* mean_psnr_db) {
  std::vector<std::vector<float>> renders;
  auto keep = [&](const View&, const std::vector<float>& rgb) {
    renders.push_back(rgb);
    return absl::OkStatus();
  };
  absl::StatusOr<EvalResult> r = EvaluateViews(engine, scene, views, background, keep);
  if (!r.ok()) return r.status();
  *mean_psnr_db = r->mean.psnr;
  return renders;
}

}  // namespace

absl::StatusOr<ClipSeamMeter> ClipSeamMeter::Create(const ClipSet& set, const DriveLog& log, double resolution_scale) {
  if (static_cast<int>(log.frames.size()) < set.num_frames) {
    return absl::InvalidArgumentError(absl::StrCat("the log has ", log.frames.size(), " frames, the clip set ",
                                                   set.num_frames));
  }
  ClipSeamMeter m;
  m.num_clips_ = static_cast<int>(set.clips.size());
  const size_t num_seams = set.clips.empty() ? 0 : set.clips.size() - 1;
  m.seams_.resize(num_seams);
  m.views_.resize(num_seams);
  m.earlier_.resize(num_seams);
  for (size_t k = 0; k < num_seams; ++k) {
    const ClipEntry& a = set.clips[k];
    const ClipEntry& b = set.clips[k + 1];
    ClipSeam& seam = m.seams_[k];
    seam.clip = static_cast<int>(k);
    // PickClip: nearer clip, a tie to the earlier one.
    seam.switch_time_us = a.end_us + (b.start_us - a.end_us) / 2 + 1;
    seam.frames = {a.frames.end_frame - 1, b.frames.first_frame};
    DatasetOptions dopt;
    dopt.resolution_scale = resolution_scale;
    dopt.holdout_every = 0;
    dopt.split = Split::kAll;
    dopt.load_depth = false;
    absl::StatusOr<std::vector<View>> v = LoadViews(ClipLog(log, {seam.frames[0], seam.frames[1] + 1}), dopt);
    if (!v.ok()) return v.status();
    if (v->empty()) return absl::InvalidArgumentError(absl::StrCat("seam ", k, ": no camera views"));
    for (View& view : *v) view.frame += seam.frames[0];
    seam.views = v->size();
    m.views_[k] = std::move(*v);
  }
  return m;
}

absl::Status ClipSeamMeter::AddClip(Engine& engine, int clip, const SceneForView& scene,
                                    const Eigen::Vector3f& background) {
  if (clip != next_clip_ || clip >= num_clips_) {
    return absl::FailedPreconditionError(
        absl::StrCat("ClipSeamMeter: clip ", clip, " given, clip ", next_clip_, " of ", num_clips_, " expected"));
  }
  const size_t c = static_cast<size_t>(clip);
  if (c > 0) {  // the seam before this clip, as the later clip
    ClipSeam& seam = seams_[c - 1];
    absl::StatusOr<std::vector<std::vector<float>>> later =
        RenderViews(engine, scene, background, views_[c - 1], &seam.psnr_after_db);
    if (!later.ok()) return later.status();
    double sum = 0;
    for (size_t i = 0; i < later->size(); ++i) {
      sum += Psnr(earlier_[c - 1][i].data(), (*later)[i].data(), (*later)[i].size());
    }
    seam.psnr_between_db = sum / later->size();
    earlier_[c - 1].clear();
  }
  if (c < seams_.size()) {  // the seam after it, as the earlier clip
    absl::StatusOr<std::vector<std::vector<float>>> r =
        RenderViews(engine, scene, background, views_[c], &seams_[c].psnr_before_db);
    if (!r.ok()) return r.status();
    earlier_[c] = std::move(*r);
  }
  ++next_clip_;
  return absl::OkStatus();
}

absl::StatusOr<std::vector<ClipSeam>> ClipSeamMeter::Finish() {
  if (next_clip_ != num_clips_) {
    return absl::FailedPreconditionError(
        absl::StrCat("ClipSeamMeter: ", next_clip_, " of ", num_clips_, " clips given"));
  }
  return seams_;
}

absl::StatusOr<std::vector<ClipSeam>> MeasureClipSeams(Engine& engine, const std::string& set_dir, const ClipSet& set,
                                                       const DriveLog& log, double resolution_scale) {
  absl::StatusOr<ClipSeamMeter> meter = ClipSeamMeter::Create(set, log, resolution_scale);
  if (!meter.ok()) return meter.status();
  for (size_t c = 0; c < set.clips.size(); ++c) {
    absl::StatusOr<LoadedClip> clip = LoadClip(engine, set_dir, set.clips[c]);
    if (!clip.ok()) return clip.status();
    if (absl::Status s = meter->AddClip(engine, static_cast<int>(c), clip->scene_for_view, clip->meta.background);
        !s.ok()) {
      return s;
    }
  }
  return meter->Finish();
}

}  // namespace streetsim::train
