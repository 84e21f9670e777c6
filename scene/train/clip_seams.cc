#include "scene/train/clip_seams.h"

#include <filesystem>

#include "absl/strings/str_cat.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/losses.h"
#include "scene/train/trainer.h"

namespace streetsim::train {
namespace {

// One clip's renders of `views`, clamped to [0, 1] as evaluation measures them, with their PSNR.
absl::StatusOr<std::vector<std::vector<float>>> RenderViews(Engine& engine, const std::string& dir,
                                                            const std::vector<View>& views, double* mean_psnr_db) {
  absl::StatusOr<SceneMeta> meta = ReadSceneMeta(dir);
  if (!meta.ok()) return meta.status();
  absl::StatusOr<GaussianStore> store = ReadGaussianPly((std::filesystem::path(dir) / "scene.ply").string());
  if (!store.ok()) return store.status();
  std::vector<std::vector<float>> renders;
  auto keep = [&](const View&, const std::vector<float>& rgb) {
    renders.push_back(rgb);
    return absl::OkStatus();
  };
  absl::StatusOr<EvalResult> r = EvaluateSceneDir(engine, dir, *store, views, meta->background, keep);
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
  std::vector<ClipSeam> seams;
  for (size_t k = 0; k + 1 < set.clips.size(); ++k) {
    const ClipEntry& a = set.clips[k];
    const ClipEntry& b = set.clips[k + 1];
    ClipSeam seam;
    seam.clip = static_cast<int>(k);
    // PickClip: nearer clip, a tie to the earlier one.
    seam.switch_time_us = a.end_us + (b.start_us - a.end_us) / 2 + 1;
    seam.frames = {a.frames.end_frame - 1, b.frames.first_frame};
    DatasetOptions dopt;
    dopt.resolution_scale = resolution_scale;
    dopt.holdout_every = 0;
    dopt.split = Split::kAll;
    dopt.load_depth = false;
    absl::StatusOr<std::vector<View>> views = LoadViews(ClipLog(log, {seam.frames[0], seam.frames[1] + 1}), dopt);
    if (!views.ok()) return views.status();
    for (View& v : *views) v.frame += seam.frames[0];
    seam.views = views->size();
    if (views->empty()) return absl::InvalidArgumentError(absl::StrCat("seam ", k, ": no camera views"));
    absl::StatusOr<std::string> dir_a = ClipPath(set_dir, a);
    if (!dir_a.ok()) return dir_a.status();
    absl::StatusOr<std::string> dir_b = ClipPath(set_dir, b);
    if (!dir_b.ok()) return dir_b.status();
    absl::StatusOr<std::vector<std::vector<float>>> ra = RenderViews(engine, *dir_a, *views, &seam.psnr_before_db);
    if (!ra.ok()) return ra.status();
    absl::StatusOr<std::vector<std::vector<float>>> rb = RenderViews(engine, *dir_b, *views, &seam.psnr_after_db);
    if (!rb.ok()) return rb.status();
    double sum = 0;
    for (size_t i = 0; i < views->size(); ++i) sum += Psnr((*ra)[i].data(), (*rb)[i].data(), (*ra)[i].size());
    seam.psnr_between_db = sum / views->size();
    seams.push_back(std::move(seam));
  }
  return seams;
}

}  // namespace streetsim::train
