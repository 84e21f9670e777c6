#include "server/scene_registry.h"

#include <chrono>
#include <filesystem>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/train/clips.h"
#include "server/actor_edits.h"
#include "server/clip_set_scene_field.h"
#include "server/echo.h"
#include "server/path_confinement.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {

constexpr int kMaxScanDepth = 3;
constexpr int kMaxScanEntries = 20000;

std::string Canonical(const std::string& p) {
  std::error_code ec;
  fs::path c = fs::canonical(p, ec);
  return ec ? std::string() : c.string();
}

}  // namespace

SceneRegistry::SceneRegistry(std::string data_root, std::string job_scenes_dir, RenderCore* core,
                             SceneLoadOptions load)
    : data_root_(std::move(data_root)), job_scenes_dir_(std::move(job_scenes_dir)), core_(core),
      load_options_(load) {
  std::lock_guard<std::mutex> lock(mu_);
  RescanLocked();
}

SceneRegistry::~SceneRegistry() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  for (std::thread& t : loaders_) t.join();
}

void SceneRegistry::RescanLocked() {
  std::map<std::string, Entry> found;
  auto add = [&](const std::string& name, const std::string& ply, const std::string& manifest_path,
                 const std::string& source) {
    if (found.count(name)) return;  // data root first, then jobs
    Entry e;
    e.name = name;
    e.ply_path = ply;
    e.source = source;
    absl::StatusOr<SceneManifest> m = ReadSceneDirManifest(manifest_path);
    if (m.ok()) {
      e.manifest = std::make_shared<SceneManifest>(std::move(*m));
    } else {
      e.manifest_error = std::string(m.status().message());
    }
    found.emplace(name, std::move(e));
  };
  // A clip set (DIR/clips.json, docs/training.md "Clips") is one scene over its clips' time
  // ranges (clip_set_scene_field.h); each clip directory is also a scene of its own.
  auto add_clip_set = [&](const std::string& name, const std::string& clips_json, const std::string& source) {
    if (found.count(name)) return;
    Entry e;
    e.name = name;
    e.ply_path = clips_json;
    e.clip_set = true;
    e.source = source;
    absl::StatusOr<SceneManifest> m = ReadClipSetManifest(fs::path(clips_json).parent_path().string());
    if (m.ok()) {
      e.manifest = std::make_shared<SceneManifest>(std::move(*m));
    } else {
      e.manifest_error = absl::StrCat("clip set: ", m.status().message());
    }
    found.emplace(name, std::move(e));
  };
  auto scan = [&](const std::string& root, const std::string& source, bool bare_ply) {
    const std::string real_root = Canonical(root);
    if (real_root.empty()) return;
    std::error_code ec;
    fs::recursive_directory_iterator it(real_root, fs::directory_options::skip_permission_denied, ec);
    int count = 0;
    for (; !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
      if (++count > kMaxScanEntries) break;
      if (it.depth() >= kMaxScanDepth - 1) it.disable_recursion_pending();
      const fs::path& p = it->path();
      std::error_code ec2;
      if (it->is_directory(ec2)) {
        const std::string clips = Canonical((p / train::kClipManifestName).string());
        if (!clips.empty() && IsInside(real_root, clips)) {
          add_clip_set(fs::relative(p, real_root).generic_string(), clips, source);
          continue;  // its clip directories are still scanned
        }
        const std::string ply = (p / "scene.ply").string();
        const std::string real = Canonical(ply);
        if (!real.empty() && IsInside(real_root, real)) {
          add(fs::relative(p, real_root).generic_string(), real, (p / "scene.json").string(), source);
        }
      } else if (bare_ply && p.extension() == ".ply" && p.filename() != "scene.ply") {
        const std::string real = Canonical(p.string());
        if (!real.empty() && IsInside(real_root, real)) {
          std::string name = fs::relative(p, real_root).generic_string();
          name.resize(name.size() - 4);
          add(name, real, "", source);
        }
      }
    }
  };
  scan(data_root_, "data_root", true);
  if (!job_scenes_dir_.empty()) scan(job_scenes_dir_, "job", false);
  // Keep the resident state of scenes still present at the same path.
  for (auto& [name, e] : found) {
    auto old = entries_.find(name);
    if (old != entries_.end() && old->second.ply_path == e.ply_path) {
      e.state = old->second.state;
      e.error = old->second.error;
      e.loaded = old->second.loaded;
      e.generation = old->second.generation;
    }
  }
  // Scenes that vanished from disk but are loading stay until their load ends.
  for (auto& [name, e] : entries_) {
    if (!found.count(name) && e.state == v1::SCENE_STATE_LOADING) found.emplace(name, e);
  }
  entries_ = std::move(found);
}

SceneRegistry::Entry* SceneRegistry::FindLocked(const std::string& name, bool rescan) {
  auto it = entries_.find(name);
  if (it == entries_.end() && rescan) {
    RescanLocked();
    it = entries_.find(name);
  }
  return it == entries_.end() ? nullptr : &it->second;
}

void SceneRegistry::FillScene(const Entry& e, bool with_trajectory, v1::Scene* out) const {
  out->set_name(e.name);
  out->set_state(e.state);
  out->set_source(e.source);
  out->set_error(!e.manifest_error.empty() ? e.manifest_error : e.error);
  if (e.manifest) {
    const SceneManifest& m = *e.manifest;
    out->set_has_time_range(m.has_time_range);
    out->set_start_time_us(m.start_us);
    out->set_end_time_us(m.end_us);
    for (const RigCamera& c : m.cameras) {
      v1::CameraSpec* spec = out->mutable_rig()->add_cameras();
      spec->set_sensor_id(c.sensor_id);
      IntrinsicsToProto(c.intrinsics, spec->mutable_intrinsics());
      PoseToProto(c.T_ego_from_cam, spec->mutable_t_ego_from_sensor());
    }
    for (const RigLidar& l : m.lidars) {
      v1::LidarSpec* spec = out->mutable_rig()->add_lidars();
      spec->set_sensor_id(l.sensor_id);
      PoseToProto(l.T_ego_from_lidar, spec->mutable_t_ego_from_sensor());
      spec->set_sweep_duration_us(l.sweep_duration_us);
    }
    if (with_trajectory) {
      for (const TimedEgoPose& p : m.ego_trajectory) {
        v1::TimedPose* tp = out->add_ego_trajectory();
        tp->set_time_us(p.time_us);
        PoseToProto(p.T_world_from_ego, tp->mutable_t_world_from_ego());
      }
    }
  }
  if (e.loaded) {
    out->set_num_gaussians(e.loaded->num_gaussians);
    v1::Bounds* b = out->mutable_bounds();
    b->mutable_min_m()->set_x(e.loaded->min_m.x());
    b->mutable_min_m()->set_y(e.loaded->min_m.y());
    b->mutable_min_m()->set_z(e.loaded->min_m.z());
    b->mutable_max_m()->set_x(e.loaded->max_m.x());
    b->mutable_max_m()->set_y(e.loaded->max_m.y());
    b->mutable_max_m()->set_z(e.loaded->max_m.z());
    out->set_load_time_s(e.loaded->load_time_s);
    const FieldStats field_stats = e.loaded->field->stats();
    out->set_has_field(field_stats.has_field);
    out->set_num_dynamic_gaussians(field_stats.num_dynamic);
    out->set_field_evaluations(field_stats.field_evaluations);
    out->set_field_device(field_stats.device);
    out->set_field_serving(field_stats.serving);
    out->set_field_form_error_m(field_stats.form_error_m);
    if (e.loaded->actors) ActorsToProto(*e.loaded->actors, with_trajectory, out);
  }
}

std::vector<v1::Scene> SceneRegistry::List() {
  std::lock_guard<std::mutex> lock(mu_);
  RescanLocked();
  std::vector<v1::Scene> out;
  for (const auto& [name, e] : entries_) {
    out.emplace_back();
    FillScene(e, false, &out.back());
  }
  return out;
}

static absl::Status UnknownScene(const std::string& name) {
  return absl::NotFoundError(absl::StrCat("unknown scene ", Echo(name), " (see ListScenes)"));
}

absl::StatusOr<v1::Scene> SceneRegistry::Get(const std::string& name) {
  std::lock_guard<std::mutex> lock(mu_);
  Entry* e = FindLocked(name, true);
  if (!e) return UnknownScene(name);
  v1::Scene out;
  FillScene(*e, true, &out);
  return out;
}

absl::StatusOr<std::shared_ptr<const SceneManifest>> SceneRegistry::Manifest(const std::string& name) {
  std::lock_guard<std::mutex> lock(mu_);
  Entry* e = FindLocked(name, true);
  if (!e) return UnknownScene(name);
  if (!e->manifest) {
    return absl::FailedPreconditionError(absl::StrCat("scene ", Echo(name), ": ", e->manifest_error));
  }
  return e->manifest;
}

bool SceneRegistry::Exists(const std::string& name) {
  std::lock_guard<std::mutex> lock(mu_);
  return FindLocked(name, true) != nullptr;
}

int SceneRegistry::num_loaded() {
  std::lock_guard<std::mutex> lock(mu_);
  int n = 0;
  for (const auto& [name, e] : entries_) n += e.loaded != nullptr;
  return n;
}

void SceneRegistry::StartLoadLocked(Entry* e) {
  e->state = v1::SCENE_STATE_LOADING;
  e->error.clear();
  const uint64_t generation = ++e->generation;
  const std::string name = e->name;
  const std::string path = e->ply_path;
  const bool clip_set = e->clip_set;
  loaders_.emplace_back([this, name, path, clip_set, generation] {
    const auto t0 = std::chrono::steady_clock::now();
    const SceneUploader upload = [this](const GaussianStore& g) { return core_->Upload(g); };
    absl::StatusOr<std::shared_ptr<LoadedScene>> result =
        clip_set ? LoadClipSet(fs::path(path).parent_path().string(), upload, load_options_)
                 : LoadSceneFile(path, upload, load_options_);
    std::lock_guard<std::mutex> lock(mu_);
    auto it = entries_.find(name);
    if (it == entries_.end() || it->second.generation != generation) return;  // unloaded meanwhile
    const double load_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (result.ok()) {
      (*result)->load_time_s = load_s;
      it->second.loaded = std::move(*result);
      it->second.state = v1::SCENE_STATE_READY;
      const FieldStats field_stats = it->second.loaded->field->stats();
      const std::string dynamic =
          field_stats.has_field
              ? absl::StrCat(", field: ", field_stats.num_dynamic, " dynamic on ", field_stats.device)
              : std::string();
      LOG(INFO) << "scene " << name << " loaded (" << it->second.loaded->num_gaussians << " Gaussians" << dynamic
                << ", " << load_s << " s)";
    } else {
      it->second.state = v1::SCENE_STATE_FAILED;
      it->second.error = std::string(result.status().message());
      LOG(WARNING) << "scene " << name << " failed to load: " << it->second.error;
    }
    cv_.notify_all();
  });
}

absl::Status SceneRegistry::WaitLoadedLocked(std::unique_lock<std::mutex>& lock, const std::string& name,
                                             const CancelCheck& cancel) {
  while (true) {
    Entry* e = FindLocked(name, false);
    if (!e) return UnknownScene(name);
    if (e->state == v1::SCENE_STATE_READY) return absl::OkStatus();
    if (e->state == v1::SCENE_STATE_FAILED) {
      return absl::FailedPreconditionError(absl::StrCat("scene ", Echo(name), " failed to load: ", e->error));
    }
    if (e->state != v1::SCENE_STATE_LOADING) StartLoadLocked(e);
    if (cancel) {
      if (absl::Status s = cancel(); !s.ok()) return s;
    }
    if (stopping_) return absl::UnavailableError("server shutting down");
    cv_.wait_for(lock, std::chrono::milliseconds(20));
  }
}

absl::StatusOr<v1::Scene> SceneRegistry::Load(const std::string& name, bool wait, const CancelCheck& cancel) {
  std::unique_lock<std::mutex> lock(mu_);
  Entry* e = FindLocked(name, true);
  if (!e) return UnknownScene(name);
  if (!e->manifest) {
    return absl::FailedPreconditionError(absl::StrCat("scene ", Echo(name), ": ", e->manifest_error));
  }
  if (e->state != v1::SCENE_STATE_READY && e->state != v1::SCENE_STATE_LOADING) StartLoadLocked(e);
  if (wait) {
    if (absl::Status s = WaitLoadedLocked(lock, name, cancel); !s.ok()) return s;
  }
  e = FindLocked(name, false);
  if (!e) return UnknownScene(name);
  v1::Scene out;
  FillScene(*e, false, &out);
  return out;
}

absl::Status SceneRegistry::Unload(const std::string& name) {
  std::lock_guard<std::mutex> lock(mu_);
  Entry* e = FindLocked(name, true);
  if (!e) return UnknownScene(name);
  e->loaded.reset();
  e->state = v1::SCENE_STATE_AVAILABLE;
  e->error.clear();
  ++e->generation;
  cv_.notify_all();
  return absl::OkStatus();
}

absl::StatusOr<SceneHandle> SceneRegistry::Acquire(const std::string& name, const CancelCheck& cancel) {
  std::unique_lock<std::mutex> lock(mu_);
  Entry* e = FindLocked(name, true);
  if (!e) return UnknownScene(name);
  if (!e->manifest) {
    return absl::FailedPreconditionError(absl::StrCat("scene ", Echo(name), ": ", e->manifest_error));
  }
  if (e->state == v1::SCENE_STATE_FAILED) StartLoadLocked(e);  // one more try
  if (absl::Status s = WaitLoadedLocked(lock, name, cancel); !s.ok()) return s;
  e = FindLocked(name, false);
  return SceneHandle{name, e->manifest, e->loaded};
}

}  // namespace streetsim::server
