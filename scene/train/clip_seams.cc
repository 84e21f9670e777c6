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

// A clip scene loaded once, as `streetsim eval` loads it: scene.ply, field.bin if any, its sky.
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

// The clip's renders of `views`, clamped to [0, 1] as evaluation measures them, and their mean PSNR.
absl::StatusOr<std::vector<std::vector<float>>> RenderViews(Engine& engine, const LoadedClip& clip,
                                                            const std::vector<View>& views, double* mean_psnr_db) {
  std::vector<std::vector<float>> renders;
  auto keep = [&](const View&, const std::vector<float>& rgb) {
    renders.push_back(rgb);
    return absl::OkStatus();
  };
  absl::StatusOr<EvalResult> r = EvaluateViews(engine, clip.scene_for_view, views, clip.meta.background, keep);
  if (!r.ok()) return r.status();
  *mean_psnr_db = r->mean.psnr;
  return renders;
}

}  // namespace

absl::StatusOr<std::vector<ClipSeam>> MeasureClipSeams(Engine& engine, const std::string& set_dir, const ClipSet& set,
                                                       const DriveLog& log, double resolution_scale) {
  if (static_cast<int>(log.frames.size()) < set.num_frames) {
    return absl::InvalidArgumentError(absl::StrCat("the log has ", log.frames.size(), " frames, the clip set ",
                                                   set.num_frames));
  }
  if (set.clips.empty()) return std::vector<ClipSeam>{};
  const size_t num_seams = set.clips.size() - 1;
  std::vector<ClipSeam> seams(num_seams);
  std::vector<std::vector<View>> views(num_seams);
  for (size_t k = 0; k < num_seams; ++k) {
    const ClipEntry& a = set.clips[k];
    const ClipEntry& b = set.clips[k + 1];
    ClipSeam& seam = seams[k];
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
    views[k] = std::move(*v);
  }
  // Each clip is loaded once and renders the seam before it (as the later clip) and the one after
  // it (as the earlier); the earlier clip's renders wait for the later one's.
  std::vector<std::vector<std::vector<float>>> earlier(num_seams);
  for (size_t c = 0; c < set.clips.size(); ++c) {
    absl::StatusOr<LoadedClip> clip = LoadClip(engine, set_dir, set.clips[c]);
    if (!clip.ok()) return clip.status();
    if (c > 0) {
      ClipSeam& seam = seams[c - 1];
      absl::StatusOr<std::vector<std::vector<float>>> later =
          RenderViews(engine, *clip, views[c - 1], &seam.psnr_after_db);
      if (!later.ok()) return later.status();
      double sum = 0;
      for (size_t i = 0; i < later->size(); ++i) {
        sum += Psnr(earlier[c - 1][i].data(), (*later)[i].data(), (*later)[i].size());
      }
      seam.psnr_between_db = sum / later->size();
      earlier[c - 1].clear();
    }
    if (c < num_seams) {
      absl::StatusOr<std::vector<std::vector<float>>> r = RenderViews(engine, *clip, views[c], &seams[c].psnr_before_db);
      if (!r.ok()) return r.status();
      earlier[c] = std::move(*r);
    }
  }
  return seams;
}

}  // namespace streetsim::train
