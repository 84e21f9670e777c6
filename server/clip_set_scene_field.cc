#include "server/clip_set_scene_field.h"

#include <algorithm>
#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {

absl::StatusOr<train::ClipSet> ReadSet(const std::string& dir) {
  absl::StatusOr<std::optional<train::ClipSet>> set = train::ReadClipSet(dir);
  if (!set.ok()) return set.status();
  if (!*set) return absl::NotFoundError(absl::StrCat(dir, ": no ", train::kClipManifestName));
  if ((*set)->clips.empty()) return absl::DataLossError(absl::StrCat(dir, ": a clip set without clips"));
  return std::move(**set);
}

absl::Status InClip(const train::ClipEntry& clip, const absl::Status& s) {
  return absl::Status(s.code(), absl::StrCat(clip.dir, ": ", s.message()));
}

bool SameRig(const std::vector<RigCamera>& a, const std::vector<RigCamera>& b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    const Intrinsics& p = a[i].intrinsics;
    const Intrinsics& q = b[i].intrinsics;
    if (a[i].sensor_id != b[i].sensor_id || p.width != q.width || p.height != q.height || p.fx != q.fx ||
        p.fy != q.fy || p.cx != q.cx || p.cy != q.cy ||
        !a[i].T_ego_from_cam.matrix().isApprox(b[i].T_ego_from_cam.matrix(), 1e-9)) {
      return false;
    }
  }
  return true;
}

}  // namespace

ClipSetSceneField::ClipSetSceneField(train::ClipSet set, std::vector<Clip> clips)
    : set_(std::move(set)), clips_(std::move(clips)) {}

absl::StatusOr<const DeviceScene*> ClipSetSceneField::At(int64_t time_us, Engine& engine) const {
  return clips_[ClipAt(time_us)].field->At(time_us, engine);
}

absl::StatusOr<std::shared_ptr<const HostScene>> ClipSetSceneField::HostAt(int64_t time_us) const {
  return clips_[ClipAt(time_us)].field->HostAt(time_us);
}

absl::StatusOr<std::shared_ptr<const HostScene>> ClipSetSceneField::GeometryAt(int64_t time_us) const {
  return clips_[ClipAt(time_us)].field->GeometryAt(time_us);
}

size_t ClipSetSceneField::num_gaussians() const {
  size_t n = 0;
  for (const Clip& c : clips_) n += c.field->num_gaussians();
  return n;
}

FieldStats ClipSetSceneField::stats() const {
  FieldStats sum;
  for (const Clip& c : clips_) {
    const FieldStats s = c.field->stats();
    sum.has_field = sum.has_field || s.has_field;
    sum.num_dynamic += s.num_dynamic;
    sum.field_evaluations += s.field_evaluations;
    if (!s.device.empty()) sum.device = sum.device.empty() || sum.device == s.device ? s.device : "mixed";
    if (!s.serving.empty()) sum.serving = sum.serving.empty() || sum.serving == s.serving ? s.serving : "mixed";
    sum.form_error_m = std::max(sum.form_error_m, s.form_error_m);
  }
  return sum;
}

std::optional<Eigen::Vector3f> ClipSetSceneField::BackgroundAt(int64_t time_us) const {
  return clips_[ClipAt(time_us)].background;
}

absl::StatusOr<SceneManifest> ReadClipSetManifest(const std::string& dir) {
  absl::StatusOr<train::ClipSet> set = ReadSet(dir);
  if (!set.ok()) return set.status();
  SceneManifest out;
  bool all_timed = true;
  for (size_t k = 0; k < set->clips.size(); ++k) {
    const train::ClipEntry& clip = set->clips[k];
    absl::StatusOr<std::string> path = train::ClipPath(dir, clip);
    if (!path.ok()) return InClip(clip, path.status());
    absl::StatusOr<SceneManifest> m = ReadSceneDirManifest((fs::path(*path) / "scene.json").string());
    if (!m.ok()) return InClip(clip, m.status());
    if (k == 0) {
      out.cameras = m->cameras;
      out.lidars = m->lidars;
      out.start_us = m->start_us;
      out.end_us = m->end_us;
    } else if (!SameRig(out.cameras, m->cameras)) {
      return absl::FailedPreconditionError(absl::StrCat(clip.dir, ": its camera rig differs from ", set->clips[0].dir,
                                                        "'s (a clip set is served with one rig)"));
    }
    all_timed = all_timed && m->has_time_range;
    out.start_us = std::min(out.start_us, m->start_us);
    out.end_us = std::max(out.end_us, m->end_us);
    if (!m->ego_trajectory.empty() && !out.ego_trajectory.empty() &&
        m->ego_trajectory.front().time_us <= out.ego_trajectory.back().time_us) {
      return absl::FailedPreconditionError(absl::StrCat(
          clip.dir, ": its ego trajectory starts at ", m->ego_trajectory.front().time_us,
          " us, not after the previous clips' end (", out.ego_trajectory.back().time_us, " us)"));
    }
    out.ego_trajectory.insert(out.ego_trajectory.end(), m->ego_trajectory.begin(), m->ego_trajectory.end());
  }
  out.has_time_range = all_timed;
  if (!all_timed) out.start_us = out.end_us = 0;
  return out;
}

absl::StatusOr<std::shared_ptr<LoadedScene>> LoadClipSet(const std::string& dir, const SceneUploader& upload,
                                                         const SceneLoadOptions& load) {
  absl::StatusOr<train::ClipSet> set = ReadSet(dir);
  if (!set.ok()) return set.status();
  auto loaded = std::make_shared<LoadedScene>();
  std::vector<ClipSetSceneField::Clip> clips;
  bool any_bounds = false;
  for (const train::ClipEntry& clip : set->clips) {
    absl::StatusOr<std::string> path = train::ClipPath(dir, clip);
    if (!path.ok()) return InClip(clip, path.status());
    absl::StatusOr<SceneManifest> m = ReadSceneDirManifest((fs::path(*path) / "scene.json").string());
    if (!m.ok()) return InClip(clip, m.status());
    absl::StatusOr<std::shared_ptr<LoadedScene>> one =
        LoadSceneFile((fs::path(*path) / "scene.ply").string(), upload, load);
    if (!one.ok()) return InClip(clip, one.status());
    loaded->num_gaussians += (*one)->num_gaussians;
    if ((*one)->num_gaussians > 0) {
      loaded->min_m = any_bounds ? loaded->min_m.cwiseMin((*one)->min_m) : (*one)->min_m;
      loaded->max_m = any_bounds ? loaded->max_m.cwiseMax((*one)->max_m) : (*one)->max_m;
      any_bounds = true;
    }
    clips.push_back({std::move((*one)->field), m->background});
  }
  loaded->field = std::make_unique<ClipSetSceneField>(std::move(*set), std::move(clips));
  return loaded;
}

}  // namespace streetsim::server
