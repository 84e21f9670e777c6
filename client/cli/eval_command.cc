// streetsim eval: PSNR, SSIM and LiDAR depth error of a trained scene on a log's held-out (or
// training) frames, and LiDAR metrics of the scene's rendered sweeps against the real scans
// (scene/train/lidar_eval.h; --no-lidar skips them). JSON on stdout (a contract other tools read),
// a table on stderr.
#include <cstdio>
#include <filesystem>
#include <map>
#include <set>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "render/engine.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "scene/train/dynamic_pixels.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/lidar_eval.h"
#include "scene/train/trainer.h"

namespace streetsim {
namespace {

int Fail(int code, const absl::Status& status) { return ReportFailure("eval", code, status); }

nlohmann::json Metrics(const train::FrameMetrics& m) {
  nlohmann::json j;
  j["psnr"] = m.psnr;
  j["ssim"] = m.ssim;
  j["depth_median_abs_m"] = m.depth_median_abs_m >= 0 ? nlohmann::json(m.depth_median_abs_m) : nlohmann::json(nullptr);
  j["depth_within_5pct"] = m.depth_within_5pct >= 0 ? nlohmann::json(m.depth_within_5pct) : nlohmann::json(nullptr);
  // PSNR* (scene/train/dynamic_pixels.h); null: no dynamic (static) pixel in the view(s).
  j["psnr_dynamic"] = m.psnr_dynamic >= 0 ? nlohmann::json(m.psnr_dynamic) : nlohmann::json(nullptr);
  j["psnr_static"] = m.psnr_static >= 0 ? nlohmann::json(m.psnr_static) : nlohmann::json(nullptr);
  return j;
}

nlohmann::json Defined(double v) { return v >= 0 ? nlohmann::json(v) : nlohmann::json(nullptr); }

void AddLidar(const train::LidarFrameMetrics& m, nlohmann::json* j) {
  (*j)["lidar_range_median_abs_m"] = Defined(m.range_median_abs_m);
  (*j)["lidar_chamfer_m"] = Defined(m.chamfer_m);
  (*j)["lidar_drop_accuracy"] = Defined(m.drop_accuracy);
  (*j)["lidar_intensity_rmse"] = Defined(m.intensity_rmse);
  (*j)["lidar_rays"] = m.rays;
}

}  // namespace

int RunEvalCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args =
      ParsedArgs::Parse(argv, {{"scene"}, {"log"}, {"split"}, {"holdout-every"}, {"resolution-scale"}, {"backend"},
                                {"no-lidar", false}, {"lidar-columns"},
                                {"lidar-static-sweep", false}});
  if (!args.ok()) return Fail(2, args.status());
  if (!args->positional().empty()) {
    return Fail(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  absl::StatusOr<std::string> scene_dir = args->Required("scene");
  if (!scene_dir.ok()) return Fail(2, scene_dir.status());
  absl::StatusOr<std::string> log_path = args->Required("log");
  if (!log_path.ok()) return Fail(2, log_path.status());
  const std::string split = args->Get("split").value_or("test");
  if (split != "test" && split != "train") return Fail(2, absl::InvalidArgumentError("--split must be test or train"));
  absl::StatusOr<train::SceneMeta> meta = train::ReadSceneMeta(*scene_dir);
  if (!meta.ok()) return Fail(2, meta.status());
  train::DatasetOptions dopt;
  dopt.holdout_every = meta->holdout_every;
  dopt.resolution_scale = meta->resolution_scale;
  if (auto v = args->Get("holdout-every"); v && (!absl::SimpleAtoi(*v, &dopt.holdout_every) || dopt.holdout_every < 0 ||
                                                 dopt.holdout_every == 1)) {
    return Fail(2, absl::InvalidArgumentError("--holdout-every must be 0 (none) or >= 2"));
  }
  if (auto v = args->Get("resolution-scale"); v && (!absl::SimpleAtod(*v, &dopt.resolution_scale) ||
                                                    !(dopt.resolution_scale > 0 && dopt.resolution_scale <= 1))) {
    return Fail(2, absl::InvalidArgumentError("--resolution-scale must be in (0, 1]"));
  }
  Backend backend = Backend::kCpu;
  if (auto v = args->Get("backend")) {
    absl::StatusOr<Backend> b = ParseBackend(*v);
    if (!b.ok()) return Fail(2, b.status());
    backend = *b;
  }
  const bool lidar = !args->Has("no-lidar");
  train::LidarEvalOptions lopt;
  if (auto v = args->Get("lidar-columns");
      v && (!absl::SimpleAtoi(*v, &lopt.columns) || lopt.columns < 16 || lopt.columns > 65536)) {
    return Fail(2, absl::InvalidArgumentError("--lidar-columns must be in 16..65536"));
  }
  lopt.rolling_sweep = !args->Has("lidar-static-sweep");
  dopt.split = split == "test" ? train::Split::kTest : train::Split::kTrain;
  if (split == "test" && dopt.holdout_every == 0) {
    return Fail(2, absl::InvalidArgumentError("--split test needs --holdout-every > 0"));
  }
  const std::string ply = (std::filesystem::path(*scene_dir) / "scene.ply").string();
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(ply);
  if (!store.ok()) return Fail(2, store.status());
  absl::StatusOr<DriveLog> log = OpenLog(*log_path);
  if (!log.ok()) return Fail(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  absl::StatusOr<std::vector<train::View>> views = train::LoadViews(*log, dopt);
  if (!views.ok()) return Fail(2, views.status());
  if (views->empty()) return Fail(2, absl::InvalidArgumentError(absl::StrCat("the log has no ", split, " views")));
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(backend);
  if (!engine.ok()) return Fail(1, engine.status());
  if (absl::Status s = train::AttachDynamicPixels(*log, &*views); !s.ok()) return Fail(1, s);
  // A field scene (DIR/field.bin) is deformed at each view's time.
  absl::StatusOr<train::EvalResult> r = train::EvaluateSceneDir(**engine, *scene_dir, *store, *views, meta->background);
  if (!r.ok()) return Fail(1, r.status());

  // LiDAR: every evaluated frame with a scan, once per frame (a frame may have several views).
  std::map<int, train::LidarFrameMetrics> lidar_by_frame;
  train::LidarEvalResult lidar_result;
  std::string reflectance_source = "constant 0.5 (scene.ply has no reflectance property)";
  if (lidar) {
    absl::StatusOr<std::optional<std::vector<float>>> refl = train::ReadPlyReflectance(ply, store->size());
    if (!refl.ok()) return Fail(2, refl.status());
    if (refl->has_value()) reflectance_source = "scene.ply reflectance";
    std::set<int> frames;
    for (const train::View& v : *views) frames.insert(v.frame);
    // A field scene's sweeps, like its views, are rendered deformed at the frame's time.
    absl::StatusOr<std::shared_ptr<const field::DeformationField>> f = train::LoadSceneField(*scene_dir);
    if (!f.ok()) return Fail(2, f.status());
    absl::StatusOr<train::LidarEvalResult> lr =
        train::EvaluateLidar(*log, std::vector<int>(frames.begin(), frames.end()), *store,
                             refl->has_value() ? &**refl : nullptr, lopt, train::MakeStoreAtTime(*f, *store));
    if (!lr.ok()) return Fail(1, lr.status());
    lidar_result = std::move(*lr);
    for (const train::LidarFrameMetrics& m : lidar_result.frames) lidar_by_frame[m.frame] = m;
  }
  const bool have_lidar = !lidar_by_frame.empty();

  nlohmann::json j;
  j["mean"] = Metrics(r->mean);
  if (have_lidar) {
    AddLidar(lidar_result.mean, &j["mean"]);
    j["lidar_reflectance"] = reflectance_source;
  }
  j["split"] = split;
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
    nlohmann::json f = Metrics(m);
    f["name"] = m.name;
    f["frame"] = m.frame;
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
  if (have_lidar) lidar_columns(lidar_result.mean);
  std::fprintf(stderr, "\n");
  if (have_lidar) std::fprintf(stderr, "lidar intensity: %s\n", reflectance_source.c_str());
  std::printf("%s\n", j.dump(2).c_str());
  return 0;
}

}  // namespace streetsim
