// streetsim init: the initial Gaussian scene of a driving log, written as an INRIA 3DGS PLY.
#include <cstdio>
#include <filesystem>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "scene/gaussians/ply_io.h"
#include "scene/init/initial_scene.h"
#include "scene/log/open_log.h"
#include "scene/log/scene_manifest.h"

namespace streetsim {
namespace {

int FailInit(int code, const absl::Status& status) { return ReportFailure("init", code, status); }

absl::Status PositiveDouble(const ParsedArgs& args, const std::string& flag, double* value) {
  if (auto v = args.Get(flag); v && (!absl::SimpleAtod(*v, value) || !(*value > 0) || !(*value < 1e6))) {
    return absl::InvalidArgumentError(absl::StrCat("--", flag, " must be a positive number"));
  }
  return absl::OkStatus();
}

}  // namespace

int RunInitCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(
      argv, {{"out"}, {"frames"}, {"voxel"}, {"max-range"}, {"sky", false}, {"drop-dynamic", false},
             {"random-points"}});
  if (!args.ok()) return FailInit(2, args.status());
  if (args->positional().size() != 1) return FailInit(2, absl::InvalidArgumentError("expects exactly one log PATH"));
  absl::StatusOr<std::string> out = args->Required("out");
  if (!out.ok()) return FailInit(2, out.status());
  if (std::filesystem::path(*out).extension() != ".ply") {
    return FailInit(2, absl::InvalidArgumentError(absl::StrCat("--out ", *out, ": must be a .ply")));
  }
  InitOptions options;
  if (auto f = args->Get("frames")) {
    absl::StatusOr<FrameRange> r = ParseFrameRange(*f);
    if (!r.ok()) return FailInit(2, r.status());
    options.frames = *r;
  }
  if (absl::Status s = PositiveDouble(*args, "voxel", &options.voxel_m); !s.ok()) return FailInit(2, s);
  if (absl::Status s = PositiveDouble(*args, "max-range", &options.max_range_m); !s.ok()) return FailInit(2, s);
  if (auto n = args->Get("random-points"); n && (!absl::SimpleAtoi(*n, &options.random_points) ||
                                                 options.random_points < 1 || options.random_points > 50'000'000)) {
    return FailInit(2, absl::InvalidArgumentError("--random-points must be in 1..50000000"));
  }
  options.sky = args->Has("sky");
  options.drop_dynamic = args->Has("drop-dynamic");

  absl::StatusOr<DriveLog> log = OpenLog(args->positional()[0]);
  if (!log.ok()) return FailInit(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  InitStats stats;
  absl::StatusOr<GaussianStore> store = BuildInitialScene(*log, options, &stats);
  if (!store.ok()) {
    return FailInit(absl::IsInvalidArgument(store.status()) || absl::IsFailedPrecondition(store.status()) ||
                        absl::IsNotFound(store.status()) || absl::IsDataLoss(store.status())
                    ? 2 : 1,
                store.status());
  }
  if (absl::Status s = WriteGaussianPly(*store, *out); !s.ok()) return FailInit(1, s);
  // A scene directory (DIR/scene.ply) also gets DIR/scene.json with the log's camera rig, time
  // range and ego trajectory, which `streetsim serve` reads (docs/server.md).
  const std::filesystem::path out_path(*out);
  if (out_path.filename() == "scene.ply") {
    const std::filesystem::path dir = out_path.has_parent_path() ? out_path.parent_path() : ".";
    const std::string manifest = (dir / "scene.json").string();
    if (absl::Status s = WriteSceneManifest(*log, std::filesystem::absolute(dir).filename().string(), manifest);
        !s.ok()) {
      return FailInit(1, s);
    }
  }
  std::fprintf(stderr,
               "streetsim init: %zu Gaussians from %s (%d frames; %zu LiDAR points -> %zu voxels, %zu seen "
               "by a camera, %zu sky), median scale %.3f m, %.1f s -> %s\n",
               stats.gaussians, stats.source.c_str(), stats.frames_used, stats.lidar_points_raw, stats.voxels,
               stats.seen, stats.sky_points, stats.median_scale_m, stats.seconds, out->c_str());
  for (const std::string& n : stats.notes) std::fprintf(stderr, "streetsim init: note: %s\n", n.c_str());
  return 0;
}

}  // namespace streetsim
