// streetsim eval: PSNR, SSIM and LiDAR depth error of a trained scene on a log's held-out (or
// training) frames, and LiDAR metrics of the scene's rendered sweeps against the real scans
// (scene/eval/lidar_eval.h; --no-lidar skips them). JSON on stdout (a contract other tools read),
// a table on stderr.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <map>
#include <optional>
#include <set>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "client/cli/static_skip_flags.h"
#include "render/engine.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "scene/train/clip_seams.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_pixels.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/eval_outputs.h"
#include "scene/eval/lidar_eval.h"
#include "scene/eval/metrics_json.h"
#include "scene/train/pose_refinement.h"
#include "scene/eval/served_scene.h"
#include "scene/train/trainer.h"

namespace streetsim {
namespace {

int FailEval(int code, const absl::Status& status) { return ReportFailure("eval", code, status); }

// --decomposition DIR / --video PATH [--video-fps F] (scene/eval/eval_outputs.h); the options stay
// empty when neither is given.
absl::StatusOr<train::EvalOutputOptions> ParseOutputOptions(const ParsedArgs& args) {
  train::EvalOutputOptions o;
  o.decomposition_dir = args.Get("decomposition").value_or("");
  o.video_path = args.Get("video").value_or("");
  if (args.Has("decomposition") && o.decomposition_dir.empty()) {
    return absl::InvalidArgumentError("--decomposition needs a directory");
  }
  if (args.Has("video") && o.video_path.empty()) return absl::InvalidArgumentError("--video needs a file (.avi or .mp4)");
  if (auto v = args.Get("video-fps")) {
    if (o.video_path.empty()) return absl::InvalidArgumentError("--video-fps needs --video");
    if (!absl::SimpleAtod(*v, &o.video_fps) || !(o.video_fps > 0 && o.video_fps <= 1000)) {
      return absl::InvalidArgumentError("--video-fps must be in (0, 1000]");
    }
  }
  if (absl::Status s = train::PrepareEvalOutputs(o); !s.ok()) return s;
  return o;
}

nlohmann::json OutputsJson(const train::EvalOutputOptions& o, const train::EvalOutputSummary& s) {
  nlohmann::json j = nlohmann::json::object();
  if (s.split) {
    nlohmann::json d;
    d["dir"] = o.decomposition_dir.empty() ? nlohmann::json(nullptr) : nlohmann::json(o.decomposition_dir);
    d["views"] = s.decomposition_views;
    d["static_gaussians"] = s.split->static_gaussians;
    d["dynamic_gaussians"] = s.split->dynamic_gaussians;
    d["has_field"] = s.split->scenes_with_field > 0;
    if (s.split->scenes_with_field == 0) d["note"] = "no field.bin: every Gaussian is static";
    j["decomposition"] = d;
  }
  if (s.video) {
    j["video"] = {{"path", s.video->path},     {"frames", s.video->frames}, {"width", s.video->width},
                  {"height", s.video->height}, {"fps", s.video->fps},       {"codec", s.video->codec},
                  {"backend", s.video->backend}};
  }
  return j;
}

void AddLidar(const train::LidarFrameMetrics& m, nlohmann::json* j) {
  (*j)["lidar_range_median_abs_m"] = train::MetricOrNull(m.range_median_abs_m);
  (*j)["lidar_chamfer_m"] = train::MetricOrNull(m.chamfer_m);
  (*j)["lidar_drop_accuracy"] = train::MetricOrNull(m.drop_accuracy);
  (*j)["lidar_intensity_rmse"] = train::MetricOrNull(m.intensity_rmse);
  (*j)["lidar_rays"] = m.rays;
}

// What the command line asks for, checked before any work.
struct EvalRequest {
  std::string split;
  bool served = false, lidar = true, log_poses = false, exact_field = false;
  field::StaticSkipOptions skip;
  train::DatasetOptions dopt;
  Backend backend = Backend::kCpu;
  train::LidarEvalOptions lopt;
  train::EvalOutputOptions outputs;
  std::string log_path;
  // A clip set (DIR/clips.json, docs/training.md "Clips"): each view is evaluated by the clip whose
  // time range holds it (scene/train/clips.h PickClip); the settings come from the first clip.
  std::optional<train::ClipSet> clip_set;
  std::vector<std::string> scene_dirs;  // the scene, or each clip's
};

// The request, or the exit code (2) after saying why.
int ParseEvalRequest(const std::vector<std::string>& argv, EvalRequest* req) {
  std::vector<FlagSpec> flags = {{"scene"}, {"log"}, {"split"}, {"holdout-every"}, {"resolution-scale"}, {"backend"},
                                 {"no-lidar", false}, {"lidar-columns"}, {"lidar-static-sweep", false},
                                 {"decomposition"}, {"video"}, {"video-fps"}, {"served", false},
                                 {"log-poses", false}};
  flags.insert(flags.end(), StaticSkipFlags().begin(), StaticSkipFlags().end());
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, flags);
  if (!args.ok()) return FailEval(2, args.status());
  // --served: render a field scene as `streetsim serve` does (the static skip's Gaussians baked),
  // with the server's thresholds or --static-motion-m / --static-sh.
  req->served = args->Has("served");
  if (!req->served && (args->Has("static-motion-m") || args->Has("static-sh") || args->Has("field-serving"))) {
    return FailEval(2, absl::InvalidArgumentError("--static-motion-m / --static-sh / --field-serving need --served"));
  }
  if (req->served && (args->Has("decomposition") || args->Has("video"))) {
    // Their static/dynamic split is the server's default analysis, not the thresholds served here.
    return FailEval(2, absl::InvalidArgumentError("--served does not combine with --decomposition or --video"));
  }
  absl::StatusOr<field::StaticSkipOptions> skip = StaticSkipFromFlags(*args);
  if (!skip.ok()) return FailEval(2, skip.status());
  req->skip = *skip;
  absl::StatusOr<bool> exact_field = ExactFieldFromFlags(*args);
  if (!exact_field.ok()) return FailEval(2, exact_field.status());
  req->exact_field = *exact_field;
  if (!args->positional().empty()) {
    return FailEval(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  absl::StatusOr<std::string> scene_dir = args->Required("scene");
  if (!scene_dir.ok()) return FailEval(2, scene_dir.status());
  absl::StatusOr<std::string> log_path = args->Required("log");
  if (!log_path.ok()) return FailEval(2, log_path.status());
  req->log_path = *log_path;
  req->split = args->Get("split").value_or("test");
  if (req->split != "test" && req->split != "train") {
    return FailEval(2, absl::InvalidArgumentError("--split must be test or train"));
  }
  absl::StatusOr<std::optional<train::ClipSet>> clip_set = train::ReadClipSet(*scene_dir);
  if (!clip_set.ok()) return FailEval(2, clip_set.status());
  req->clip_set = std::move(*clip_set);
  req->scene_dirs = {*scene_dir};
  if (req->clip_set) {
    req->scene_dirs.clear();
    for (const train::ClipEntry& c : req->clip_set->clips) {
      absl::StatusOr<std::string> d = train::ClipPath(*scene_dir, c);
      if (!d.ok()) return FailEval(2, d.status());
      req->scene_dirs.push_back(*d);
    }
  }
  absl::StatusOr<train::SceneMeta> meta = train::ReadSceneMeta(req->scene_dirs[0]);
  if (!meta.ok()) return FailEval(2, meta.status());
  train::DatasetOptions& dopt = req->dopt;
  dopt.holdout_every = meta->holdout_every;
  dopt.resolution_scale = meta->resolution_scale;
  if (auto v = args->Get("holdout-every"); v && (!absl::SimpleAtoi(*v, &dopt.holdout_every) || dopt.holdout_every < 0 ||
                                                 dopt.holdout_every == 1)) {
    return FailEval(2, absl::InvalidArgumentError("--holdout-every must be 0 (none) or >= 2"));
  }
  if (auto v = args->Get("resolution-scale"); v && (!absl::SimpleAtod(*v, &dopt.resolution_scale) ||
                                                    !(dopt.resolution_scale > 0 && dopt.resolution_scale <= 1))) {
    return FailEval(2, absl::InvalidArgumentError("--resolution-scale must be in (0, 1]"));
  }
  if (auto v = args->Get("backend")) {
    absl::StatusOr<Backend> b = ParseBackend(*v);
    if (!b.ok()) return FailEval(2, b.status());
    req->backend = *b;
  }
  req->lidar = !args->Has("no-lidar");
  req->log_poses = args->Has("log-poses");
  if (auto v = args->Get("lidar-columns");
      v && (!absl::SimpleAtoi(*v, &req->lopt.columns) || req->lopt.columns < 16 || req->lopt.columns > 65536)) {
    return FailEval(2, absl::InvalidArgumentError("--lidar-columns must be in 16..65536"));
  }
  req->lopt.rolling_sweep = !args->Has("lidar-static-sweep");
  dopt.split = req->split == "test" ? train::Split::kTest : train::Split::kTrain;
  if (req->split == "test" && dopt.holdout_every == 0) {
    return FailEval(2, absl::InvalidArgumentError("--split test needs --holdout-every > 0"));
  }
  absl::StatusOr<train::EvalOutputOptions> output_options = ParseOutputOptions(*args);
  if (!output_options.ok()) return FailEval(2, output_options.status());
  req->outputs = *output_options;
  return 0;
}

// What the scene directories measured.
struct EvalTotals {
  std::vector<train::EvalResult> parts;
  std::vector<train::LidarEvalResult> lidar_parts;
  size_t served_static = 0, served_dynamic = 0;
  double served_analysis_s = 0;
  float served_form_position_max_m = 0;
  int served_by_form = 0;  // scenes (clips) served through their serving form
  int scenes_with_reflectance = 0, scenes_evaluated = 0, scenes_with_pose_corrections = 0;
};

// The scene as `streetsim serve` serves it (--served): by default its serving form (cached in
// DIR/field.serving), or the exact field. Null for a static scene (served as it is).
int ServedSceneOf(const EvalRequest& req, const std::string& dir,
                  const std::shared_ptr<const field::DeformationField>& f, const GaussianStore& store,
                  EvalTotals* totals, std::shared_ptr<field::ServedScene>* served_scene) {
  if (!f) {
    totals->served_static += store.size();
    return 0;
  }
  const auto t0 = std::chrono::steady_clock::now();
  auto make_exact = [&]() { return train::MakeExactServedScene(f, store, req.skip); };
  absl::StatusOr<std::shared_ptr<field::ServedScene>> ss =
      req.exact_field ? train::MakeServedScene(f, store, req.skip)
                      : absl::StatusOr<std::shared_ptr<field::ServedScene>>(
                            train::LoadServedScene(dir, make_exact, field::ServingFormOptions{}, req.skip));
  if (!ss.ok()) return FailEval(1, ss.status());
  if (const auto* form = dynamic_cast<const field::ServingForm*>(ss->get())) {
    totals->served_form_position_max_m = std::max(totals->served_form_position_max_m, form->error().max[0]);
    ++totals->served_by_form;
  }
  totals->served_analysis_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  *served_scene = *ss;
  totals->served_dynamic += (*ss)->num_dynamic();
  totals->served_static += (*ss)->size() - (*ss)->num_dynamic();
  return 0;
}

// One scene directory (the scene, or clip `k` of a set) on its views: images, then LiDAR sweeps;
// the decomposition / video outputs and the clip seams take its renders.
int EvaluateScene(const EvalRequest& req, const DriveLog& log, Engine& engine, size_t k, std::vector<train::View> views,
                  train::EvalOutputs* outputs, train::ClipSeamMeter* seam_meter, EvalTotals* totals) {
  const std::string& dir = req.scene_dirs[k];
  absl::StatusOr<train::SceneMeta> scene_meta = train::ReadSceneMeta(dir);  // its own learned sky
  if (!scene_meta.ok()) return FailEval(2, scene_meta.status());
  const std::string ply = (std::filesystem::path(dir) / "scene.ply").string();
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(ply);
  if (!store.ok()) return FailEval(2, store.status());
  // A run that refined its poses is measured at them (held-out views: interpolated).
  if (!req.log_poses) {
    absl::StatusOr<std::vector<train::PoseCorrection>> corrections = train::ReadPoseCorrections(dir);
    if (corrections.ok()) {
      train::ApplyPoseCorrections(*corrections, &views);
      ++totals->scenes_with_pose_corrections;
    } else if (!absl::IsNotFound(corrections.status())) {
      return FailEval(2, corrections.status());
    }
  }
  // A field scene (DIR/field.bin) is deformed at each view's time.
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> f = train::LoadSceneField(dir);
  if (!f.ok()) return FailEval(2, f.status());
  if (outputs) {
    if (absl::Status s = outputs->UseScene(*store, *f, scene_meta->background); !s.ok()) return FailEval(1, s);
  }
  std::shared_ptr<field::ServedScene> served_scene;
  if (req.served) {
    if (int rc = ServedSceneOf(req, dir, *f, *store, totals, &served_scene)) return rc;
  }
  absl::StatusOr<train::SceneForView> sv = served_scene ? train::MakeServedSceneForView(engine, served_scene)
                                                        : train::MakeSceneForView(engine, *store, *f);
  if (!sv.ok()) return FailEval(1, sv.status());
  if (seam_meter) {
    if (absl::Status s = seam_meter->AddClip(engine, static_cast<int>(k), *sv, scene_meta->background); !s.ok()) {
      return FailEval(1, s);
    }
  }
  if (views.empty()) return 0;  // a clip with no views of this split still renders its seams
  absl::StatusOr<train::EvalResult> r =
      train::EvaluateViews(engine, *sv, views, scene_meta->background,
                           outputs && !served_scene ? outputs->sink() : train::EvalFrameSink());
  if (!r.ok()) return FailEval(1, r.status());
  totals->parts.push_back(std::move(*r));
  ++totals->scenes_evaluated;
  if (!req.lidar) return 0;
  // LiDAR: every evaluated frame with a scan, once per frame (a frame may have several views).
  absl::StatusOr<std::optional<std::vector<float>>> refl = train::ReadPlyReflectance(ply, store->size());
  if (!refl.ok()) return FailEval(2, refl.status());
  totals->scenes_with_reflectance += refl->has_value();
  std::set<int> frames;
  for (const train::View& v : views) frames.insert(v.frame);
  // A field scene's sweeps, like its views, are rendered deformed at the frame's time.
  absl::StatusOr<train::LidarEvalResult> lr = train::EvaluateLidar(
      log, std::vector<int>(frames.begin(), frames.end()), *store, refl->has_value() ? &**refl : nullptr, req.lopt,
      served_scene ? train::MakeServedStoreAtTime(served_scene) : train::MakeStoreAtTime(*f, *store));
  if (!lr.ok()) return FailEval(1, lr.status());
  totals->lidar_parts.push_back(std::move(*lr));
  return 0;
}

// What the report prints: the merged metrics and the outputs' and seams' summaries.
struct EvalReport {
  train::EvalResult images;
  train::LidarEvalResult lidar;
  train::EvalOutputSummary outputs;
  std::vector<train::ClipSeam> seams;
};

// JSON on stdout (the contract other tools read) and the table on stderr.
void PrintReport(const EvalRequest& req, const DriveLog& log, const EvalTotals& totals, const EvalReport& report) {
  std::map<int, train::LidarFrameMetrics> lidar_by_frame;
  for (const train::LidarFrameMetrics& m : report.lidar.frames) lidar_by_frame[m.frame] = m;
  const int with_reflectance = totals.scenes_with_reflectance;
  const std::string reflectance_source =
      with_reflectance == totals.scenes_evaluated ? "scene.ply reflectance"
      : with_reflectance == 0                     ? "constant 0.5 (scene.ply has no reflectance property)"
                              : "scene.ply reflectance where the clip's scene.ply has it, else constant 0.5";
  const bool have_lidar = !lidar_by_frame.empty();
  const train::EvalResult* r = &report.images;

  nlohmann::json j;
  j["mean"] = train::FrameMetricsJson(r->mean);
  if (have_lidar) {
    AddLidar(report.lidar.mean, &j["mean"]);
    j["lidar_reflectance"] = reflectance_source;
  }
  j["split"] = req.split;
  // Which camera poses the views were rendered at (pose_refinement.h).
  const int corrected = totals.scenes_with_pose_corrections;
  j["poses"] = corrected == 0                         ? "log"
               : corrected == totals.scenes_evaluated ? "corrected"
                                                      : "corrected where the clip has corrections";
  const nlohmann::json outputs_json = OutputsJson(req.outputs, report.outputs);
  for (const auto& [key, value] : outputs_json.items()) j[key] = value;
  if (req.served) {
    j["served"] = {{"motion_threshold_m", req.skip.motion_threshold_m}, {"sh_threshold", req.skip.sh_threshold},
                   {"static_gaussians", totals.served_static}, {"dynamic_gaussians", totals.served_dynamic},
                   {"analysis_s", totals.served_analysis_s},
                   {"field_serving", req.exact_field ? "exact" : "served"}};
    if (!req.exact_field) {
      j["served"]["form_position_error_max_m"] = totals.served_form_position_max_m;
      j["served"]["scenes_served_by_form"] = totals.served_by_form;
    }
    std::fprintf(stderr,
                 "served as by streetsim serve: %zu static / %zu dynamic Gaussians (skip below %g m, ΔSH %g)\n",
                 totals.served_static, totals.served_dynamic, req.skip.motion_threshold_m, req.skip.sh_threshold);
  }
  if (req.clip_set) {
    j["seams"] = nlohmann::json::array();
    for (const train::ClipSeam& s : report.seams) {
      j["seams"].push_back({{"clip", s.clip}, {"switch_time_us", s.switch_time_us}, {"frames", s.frames},
                            {"views", s.views}, {"psnr_between_clips", s.psnr_between_db},
                            {"psnr_before", s.psnr_before_db}, {"psnr_after", s.psnr_after_db}});
      std::fprintf(stderr,
                   "seam clip %d | %d (frames %d, %d; %zu views): the two clips' renders %.2f dB apart; against "
                   "the images %.2f | %.2f dB\n",
                   s.clip, s.clip + 1, s.frames[0], s.frames[1], s.views, s.psnr_between_db, s.psnr_before_db,
                   s.psnr_after_db);
    }
  }
  j["frames"] = nlohmann::json::array();
  std::fprintf(stderr, "%-34s %6s %8s %7s %12s %10s", "view", "frame", "PSNR", "SSIM", "depth med m", "within 5%");
  if (have_lidar) {
    std::fprintf(stderr, " %10s %10s %8s %8s %7s", "lidar med", "chamfer m", "drop acc", "int rmse", "rays");
  }
  std::fprintf(stderr, "\n");
  auto lidar_columns = [](const train::LidarFrameMetrics& l) {
    std::fprintf(stderr, " %10.3f %10.3f %8.4f %8.4f %7zu", l.range_median_abs_m, l.chamfer_m, l.drop_accuracy,
                 l.intensity_rmse, l.rays);
  };
  for (const train::FrameMetrics& m : r->frames) {
    nlohmann::json f = train::FrameMetricsJson(m);
    f["name"] = m.name;
    f["frame"] = m.frame;
    if (req.clip_set) f["clip"] = train::PickClip(*req.clip_set, log.frames[m.frame].time_us);
    auto l = lidar_by_frame.find(m.frame);
    if (l != lidar_by_frame.end()) AddLidar(l->second, &f);
    j["frames"].push_back(f);
    std::fprintf(stderr, "%-34s %6d %8.2f %7.4f %12.3f %10.3f", m.name.c_str(), m.frame, m.psnr, m.ssim,
                 m.depth_median_abs_m, m.depth_within_5pct);
    if (l != lidar_by_frame.end()) lidar_columns(l->second);
    std::fprintf(stderr, "\n");
  }
  std::fprintf(stderr, "%-34s %6s %8.2f %7.4f %12.3f %10.3f", "mean", "", r->mean.psnr, r->mean.ssim,
               r->mean.depth_median_abs_m, r->mean.depth_within_5pct);
  if (have_lidar) lidar_columns(report.lidar.mean);
  std::fprintf(stderr, "\n");
  if (have_lidar) std::fprintf(stderr, "lidar intensity: %s\n", reflectance_source.c_str());
  std::printf("%s\n", j.dump(2).c_str());
}

}  // namespace

int RunEvalCommand(const std::vector<std::string>& argv) {
  EvalRequest req;
  if (int rc = ParseEvalRequest(argv, &req)) return rc;
  absl::StatusOr<DriveLog> log = OpenLog(req.log_path);
  if (!log.ok()) return FailEval(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  absl::StatusOr<std::vector<train::View>> all_views = train::LoadViews(*log, req.dopt);
  if (!all_views.ok()) return FailEval(2, all_views.status());
  if (all_views->empty()) {
    return FailEval(2, absl::InvalidArgumentError(absl::StrCat("the log has no ", req.split, " views")));
  }
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(req.backend);
  if (!engine.ok()) return FailEval(1, engine.status());
  if (absl::Status s = train::AttachDynamicPixels(*log, &*all_views); !s.ok()) return FailEval(1, s);
  // Decomposition images / video: fed by the evaluation's renders (UseScene once per scene).
  std::unique_ptr<train::EvalOutputs> outputs;
  if (!req.outputs.decomposition_dir.empty() || !req.outputs.video_path.empty()) {
    absl::StatusOr<std::unique_ptr<train::EvalOutputs>> o = train::EvalOutputs::Create(**engine, req.outputs);
    if (!o.ok()) return FailEval(2, o.status());
    outputs = std::move(*o);
  }
  // The views of each scene directory: all of them, or for a clip set those of each clip's times.
  std::vector<std::vector<size_t>> view_groups(1);
  if (req.clip_set) {
    view_groups = train::GroupViewsByClip(*req.clip_set, *all_views);
  } else {
    for (size_t i = 0; i < all_views->size(); ++i) view_groups[0].push_back(i);
  }
  // A clip set: how far the image jumps where a consumer crosses from one clip to the next,
  // measured with the scenes the loop loads (each clip once).
  std::optional<train::ClipSeamMeter> seam_meter;
  if (req.clip_set) {
    absl::StatusOr<train::ClipSeamMeter> m =
        train::ClipSeamMeter::Create(*req.clip_set, *log, req.dopt.resolution_scale);
    if (!m.ok()) return FailEval(1, m.status());
    seam_meter = std::move(*m);
  }
  EvalTotals totals;
  for (size_t k = 0; k < view_groups.size(); ++k) {
    if (view_groups[k].empty() && !seam_meter) continue;
    std::vector<train::View> views;
    for (size_t i : view_groups[k]) views.push_back(std::move((*all_views)[i]));
    if (int rc = EvaluateScene(req, *log, **engine, k, std::move(views), outputs.get(),
                               seam_meter ? &*seam_meter : nullptr, &totals)) {
      return rc;
    }
  }
  EvalReport report;
  report.images = totals.parts.size() == 1 ? std::move(totals.parts[0]) : train::MergeEvalResults(totals.parts);
  if (outputs) {
    absl::StatusOr<train::EvalOutputSummary> os = outputs->Finish();
    if (!os.ok()) return FailEval(1, os.status());
    report.outputs = std::move(*os);
  }
  report.lidar = totals.lidar_parts.size() == 1 ? std::move(totals.lidar_parts[0])
                                                : train::MergeLidarEvalResults(totals.lidar_parts);
  if (seam_meter) {
    absl::StatusOr<std::vector<train::ClipSeam>> s = seam_meter->Finish();
    if (!s.ok()) return FailEval(1, s.status());
    report.seams = std::move(*s);
  }
  PrintReport(req, *log, totals, report);
  return 0;
}

}  // namespace streetsim
