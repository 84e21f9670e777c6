#include "scene/actors/scene_actors.h"

#include <filesystem>
#include <optional>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_stage.h"

namespace streetsim::actors {

absl::StatusOr<ActorSet> ExtractSceneActors(const DriveLog& log, const std::string& dir,
                                            const ActorExtractionOptions& options) {
  namespace fs = std::filesystem;
  if (log.lidars.empty()) {
    return absl::FailedPreconditionError("the log has no LiDAR: actors are found in its scans");
  }
  std::error_code ec;
  if (fs::exists(fs::path(dir) / train::kClipManifestName, ec)) {
    return absl::FailedPreconditionError(absl::StrCat(dir, " is a clip set: actors are extracted per scene"));
  }
  const std::string ply = (fs::path(dir) / "scene.ply").string();
  absl::StatusOr<GaussianStore> canonical = ReadGaussianPly(ply);
  if (!canonical.ok()) return canonical.status();
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> field = train::LoadSceneField(dir);
  if (!field.ok()) return field.status();
  MovingObjectOptions tracking;
  tracking.keep_points = true;
  absl::StatusOr<MovingObjects> objects = TrackMovingObjects(log, tracking);
  if (!objects.ok()) return objects.status();

  ThreadPool pool(0);
  std::optional<GaussianStore> deformed;
  const GaussiansAt at = [&](int64_t time_us) -> absl::StatusOr<const GaussianStore*> {
    if (!*field) return &*canonical;
    absl::StatusOr<GaussianStore> d = train::DeformedStore(**field, *canonical, time_us, pool);
    if (!d.ok()) return d.status();
    deformed = std::move(*d);
    return &*deformed;
  };
  absl::StatusOr<ActorSet> set = ExtractActors(objects->tracks, at, options);
  if (!set.ok()) return set.status();
  set->scene_gaussians = canonical->size();
  set->sh_degree = canonical->sh_degree;
  absl::StatusOr<uint64_t> checksum = SceneChecksum(ply);
  if (!checksum.ok()) return checksum.status();
  set->scene_checksum = *checksum;
  if (absl::Status s = WriteActorSet(*set, dir); !s.ok()) return s;
  return set;
}

}  // namespace streetsim::actors
