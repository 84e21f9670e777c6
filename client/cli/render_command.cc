// streetsim render: one frame of a PLY scene from a CAMERA.json, written as PNG (+ float TIFFs).
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <optional>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "client/cli/args.h"
#include "client/cli/camera_json.h"
#include "client/cli/commands.h"
#include "client/cli/image_io.h"
#include "render/engine.h"
#include "render/common/thread_pool.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/trainer.h"

namespace streetsim {
namespace {

int FailRender(int code, const absl::Status& status) { return ReportFailure("render", code, status); }

absl::StatusOr<Eigen::Vector3f> ParseBackground(const std::string& text) {
  const std::vector<std::string> parts = absl::StrSplit(text, ',');
  if (parts.size() != 3) {
    return absl::InvalidArgumentError("--background takes R,G,B (three numbers in [0,1])");
  }
  Eigen::Vector3f bg;
  for (int i = 0; i < 3; ++i) {
    float v;
    if (!absl::SimpleAtof(absl::StripAsciiWhitespace(parts[i]), &v) || !std::isfinite(v) || v < 0 ||
        v > 1) {
      return absl::InvalidArgumentError(
          absl::StrCat("--background component '", parts[i], "' is not a number in [0,1]"));
    }
    bg[i] = v;
  }
  return bg;
}

absl::Status CheckExtension(const std::string& path, std::initializer_list<const char*> allowed,
                            const char* flag) {
  const std::string ext = absl::AsciiStrToLower(std::filesystem::path(path).extension().string());
  for (const char* a : allowed) {
    if (ext == a) return absl::OkStatus();
  }
  return absl::InvalidArgumentError(absl::StrCat(flag, " ", path, ": unsupported extension"));
}

}  // namespace

int RunRenderCommand(const std::vector<std::string>& argv) {
  for (const std::string& a : argv) {
    if (a == "--server" || a.rfind("--server=", 0) == 0) return RunRemoteRenderCommand(argv);
  }
  for (const std::string& a : argv) {
    if (a == "--lidar") return RunLidarRenderCommand(argv);
  }
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(
      argv, {{"ply"}, {"camera"}, {"out-rgb"}, {"out-depth"}, {"out-alpha"}, {"background"},
             {"backend"}, {"scene"}, {"time-us"}});
  if (!args.ok()) return FailRender(2, args.status());
  if (!args->positional().empty()) {
    return FailRender(2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  // --scene DIR: a trained scene directory (scene.ply, and field.bin when it is dynamic).
  if (args->Has("scene") && args->Has("ply")) {
    return FailRender(2, absl::InvalidArgumentError("give one of --ply SCENE.ply and --scene DIR, not both"));
  }
  std::string scene_dir = args->Get("scene").value_or("");
  absl::StatusOr<std::string> ply =
      args->Has("scene") ? (std::filesystem::path(scene_dir) / "scene.ply").string() : args->Required("ply");
  if (!ply.ok()) return FailRender(2, ply.status());
  std::optional<int64_t> time_us;
  if (auto v = args->Get("time-us")) {
    int64_t t = 0;
    if (!args->Has("scene")) return FailRender(2, absl::InvalidArgumentError("--time-us needs --scene DIR"));
    if (!absl::SimpleAtoi(*v, &t)) return FailRender(2, absl::InvalidArgumentError("--time-us must be an integer (microseconds)"));
    time_us = t;
  }
  // A clip set (DIR/clips.json, docs/training.md "Clips"): the clip whose time range holds T.
  if (!scene_dir.empty()) {
    absl::StatusOr<std::string> clip_dir = train::SceneDirForTime(scene_dir, time_us);
    if (!clip_dir.ok()) return FailRender(2, clip_dir.status());
    scene_dir = *clip_dir;
    ply = (std::filesystem::path(scene_dir) / "scene.ply").string();
  }
  absl::StatusOr<std::string> camera_path = args->Required("camera");
  if (!camera_path.ok()) return FailRender(2, camera_path.status());
  absl::StatusOr<std::string> out_rgb = args->Required("out-rgb");
  if (!out_rgb.ok()) return FailRender(2, out_rgb.status());
  if (absl::Status s = CheckExtension(*out_rgb, {".png", ".jpg", ".jpeg"}, "--out-rgb"); !s.ok()) return FailRender(2, s);
  const std::string out_depth = args->Get("out-depth").value_or("");
  const std::string out_alpha = args->Get("out-alpha").value_or("");
  if (args->Has("out-depth")) {
    if (absl::Status s = CheckExtension(out_depth, {".tif", ".tiff"}, "--out-depth"); !s.ok()) return FailRender(2, s);
  }
  if (args->Has("out-alpha")) {
    if (absl::Status s = CheckExtension(out_alpha, {".tif", ".tiff"}, "--out-alpha"); !s.ok()) return FailRender(2, s);
  }
  RenderOptions options;
  if (auto bg = args->Get("background")) {
    absl::StatusOr<Eigen::Vector3f> parsed = ParseBackground(*bg);
    if (!parsed.ok()) return FailRender(2, parsed.status());
    options.background = *parsed;
  } else if (!scene_dir.empty()) {
    // A trained scene renders over the sky colour it learned (DIR/train_meta.json), as the server
    // and `streetsim eval` render it: on black, its sky would look like a hole.
    absl::StatusOr<train::SceneMeta> meta = train::ReadSceneMeta(scene_dir);
    if (!meta.ok()) return FailRender(2, meta.status());
    options.background = meta->background;
  }
  absl::StatusOr<Backend> backend = ParseBackend(args->Get("backend").value_or("auto"));
  if (!backend.ok()) return FailRender(2, backend.status());

  absl::StatusOr<PinholeCamera> camera = ReadCameraJson(*camera_path);
  if (!camera.ok()) return FailRender(2, camera.status());
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(*ply);
  if (!store.ok()) return FailRender(2, store.status());
  if (!scene_dir.empty()) {
    // The field at T, clamped to the log's time range; without --time-us, the log's first time.
    absl::StatusOr<std::shared_ptr<const field::DeformationField>> f = train::LoadSceneField(scene_dir);
    if (!f.ok()) return FailRender(2, f.status());
    if (*f) {
      ThreadPool pool(0);
      absl::StatusOr<GaussianStore> d =
          train::DeformedStore(**f, *store, time_us.value_or((*f)->time_range().start_us), pool);
      if (!d.ok()) return FailRender(2, d.status());
      store = std::move(*d);
    }
  }

  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(*backend);
  if (!engine.ok()) return FailRender(1, engine.status());
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(*store);
  if (!scene.ok()) return FailRender(1, scene.status());
  options.want_depth = !out_depth.empty();
  options.want_alpha = !out_alpha.empty();
  RenderOutput out;
  if (absl::Status s = (*engine)->Render(**scene, *camera, options, &out); !s.ok()) return FailRender(1, s);

  if (absl::Status s = WriteRgb8(*out_rgb, out.width, out.height, out.rgb); !s.ok()) return FailRender(1, s);
  if (!out_depth.empty()) {
    if (absl::Status s = WriteFloatTiff(out_depth, out.width, out.height, out.depth); !s.ok()) return FailRender(1, s);
  }
  if (!out_alpha.empty()) {
    if (absl::Status s = WriteFloatTiff(out_alpha, out.width, out.height, out.alpha); !s.ok()) return FailRender(1, s);
  }
  std::fprintf(stderr,
               "streetsim render: %dx%d, %zu Gaussians (%zu visible, %zu tile instances) on %s: "
               "%.1f ms (projection %.1f, sort %.1f, blend %.1f)\n",
               out.width, out.height, out.stats.num_gaussians, out.stats.num_visible,
               out.stats.num_tile_instances, (*engine)->device_name().c_str(), out.timings.total_ms,
               out.timings.projection_ms, out.timings.sort_ms, out.timings.blend_ms);
  return 0;
}

}  // namespace streetsim
