// streetsim eval: PSNR, SSIM and LiDAR depth error of a trained scene on a log's held-out (or
// training) frames. JSON on stdout (a contract other tools read), a table on stderr.
#include <cstdio>
#include <filesystem>

#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "render/engine.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
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
  return j;
}

}  // namespace

int RunEvalCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args =
      ParsedArgs::Parse(argv, {{"scene"}, {"log"}, {"split"}, {"holdout-every"}, {"resolution-scale"}, {"backend"}});
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
  absl::StatusOr<train::EvalResult> r = train::Evaluate(**engine, *store, *views, meta->background);
  if (!r.ok()) return Fail(1, r.status());

  nlohmann::json j;
  j["mean"] = Metrics(r->mean);
  j["split"] = split;
  j["frames"] = nlohmann::json::array();
  std::fprintf(stderr, "%-34s %6s %8s %7s %12s %10s\n", "view", "frame", "PSNR", "SSIM", "depth med m", "within 5%");
  for (const train::FrameMetrics& m : r->frames) {
    nlohmann::json f = Metrics(m);
    f["name"] = m.name;
    f["frame"] = m.frame;
    j["frames"].push_back(f);
    std::fprintf(stderr, "%-34s %6d %8.2f %7.4f %12.3f %10.3f\n", m.name.c_str(), m.frame, m.psnr, m.ssim,
                 m.depth_median_abs_m, m.depth_within_5pct);
  }
  std::fprintf(stderr, "%-34s %6s %8.2f %7.4f %12.3f %10.3f\n", "mean", "", r->mean.psnr, r->mean.ssim,
               r->mean.depth_median_abs_m, r->mean.depth_within_5pct);
  std::printf("%s\n", j.dump(2).c_str());
  return 0;
}

}  // namespace streetsim
