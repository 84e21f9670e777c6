// streetsim actors: a trained scene's actors (docs/actors.md).
//   streetsim actors extract --scene DIR --log PATH   (what `streetsim train` does at its end)
//   streetsim actors list --scene DIR [--json]
#include <cstdio>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/commands.h"
#include "scene/actors/actor_set.h"
#include "scene/actors/scene_actors.h"
#include "scene/log/open_log.h"

namespace streetsim {
namespace {

int FailActors(int code, const absl::Status& status) { return ReportFailure("actors", code, status); }

void PrintTable(const actors::ActorSet& set) {
  std::fprintf(stderr, "%5s %10s %10s %18s %9s %7s %8s\n", "actor", "from_s", "to_s", "box_m (l x w x h)", "Gaussians",
               "ghost", "path_m");
  for (const actors::Actor& a : set.actors) {
    double path_m = 0;
    for (size_t k = 1; k < a.trajectory.size(); ++k) {
      path_m += (a.trajectory[k].T_world_from_actor.translation() - a.trajectory[k - 1].T_world_from_actor.translation())
                    .norm();
    }
    const Eigen::Vector3d size = 2 * a.half_extent_m;
    std::fprintf(stderr, "%5d %10.2f %10.2f %6.1f x%4.1f x%4.1f %9zu %7zu %8.1f\n", a.id, a.start_time_us() * 1e-6,
                 a.end_time_us() * 1e-6, size.x(), size.y(), size.z(), a.body_rows.size(), a.ghost_rows.size(), path_m);
  }
}

std::string SetJson(const actors::ActorSet& set) {
  nlohmann::json out = nlohmann::json::array();
  for (const actors::Actor& a : set.actors) {
    const Eigen::Vector3d start = a.trajectory.front().T_world_from_actor.translation();
    const Eigen::Vector3d end = a.trajectory.back().T_world_from_actor.translation();
    out.push_back({{"actor_id", a.id},
                   {"start_time_us", a.start_time_us()},
                   {"end_time_us", a.end_time_us()},
                   {"half_extent_m", {a.half_extent_m.x(), a.half_extent_m.y(), a.half_extent_m.z()}},
                   {"num_gaussians", a.body_rows.size()},
                   {"num_ghost_gaussians", a.ghost_rows.size()},
                   {"first_position_m", {start.x(), start.y(), start.z()}},
                   {"last_position_m", {end.x(), end.y(), end.z()}}});
  }
  return nlohmann::json{{"actors", out}}.dump(1) + "\n";
}

}  // namespace

int RunActorsCommand(const std::vector<std::string>& argv) {
  if (argv.empty() || (argv[0] != "extract" && argv[0] != "list")) {
    return FailActors(2, absl::InvalidArgumentError("usage: streetsim actors extract --scene DIR --log PATH | "
                                              "actors list --scene DIR [--json]"));
  }
  const std::string sub = argv[0];
  const std::vector<std::string> rest(argv.begin() + 1, argv.end());
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(rest, {{"scene"}, {"log"}, {"json", false}});
  if (!args.ok()) return FailActors(2, args.status());
  absl::StatusOr<std::string> scene = args->Required("scene");
  if (!scene.ok()) return FailActors(2, scene.status());
  if (sub == "list") {
    absl::StatusOr<actors::ActorSet> set = actors::ReadActorSet(*scene);
    if (!set.ok()) return FailActors(2, set.status());
    PrintTable(*set);
    if (args->Has("json")) std::fputs(SetJson(*set).c_str(), stdout);
    return 0;
  }
  absl::StatusOr<std::string> log_path = args->Required("log");
  if (!log_path.ok()) return FailActors(2, log_path.status());
  absl::StatusOr<DriveLog> log = OpenLog(*log_path);
  if (!log.ok()) return FailActors(absl::IsInternal(log.status()) ? 1 : 2, log.status());
  absl::StatusOr<actors::ActorSet> set = actors::ExtractSceneActors(*log, *scene);
  if (!set.ok()) return FailActors(absl::IsInternal(set.status()) ? 1 : 2, set.status());
  PrintTable(*set);
  std::fprintf(stderr, "streetsim actors: %zu actors -> %s/%s\n", set->actors.size(), scene->c_str(),
               actors::kActorsJson);
  if (args->Has("json")) std::fputs(SetJson(*set).c_str(), stdout);
  return 0;
}

}  // namespace streetsim
