// The catalogue of scenes the server can render, and the ones resident in the renderer.
//
// A scene is found by scanning (bounded depth 3, symlinks never followed out of the root):
//  - a directory under the data root holding scene.ply (+ optional scene.json, see
//    scene_manifest.h): named by its path relative to the data root, e.g. "kitti/0001";
//  - a bare .ply file under the data root: named by its relative path without ".ply"; a static
//    scene (any time accepted) with the default rig;
//  - a finished training job's output, <state_dir>/scenes/<name>/;
//  - a clip set (a directory with clips.json, docs/training.md "Clips"), served as one scene by
//    ClipSetSceneField (clip_set_scene_field.h) and named like a directory; its clip directories
//    are scenes of their own too.
// Names are looked up in the catalogue only; request strings never become paths.
// Loading (PLY read, field.bin and its static analysis when present, Engine::Upload) runs on its
// own thread; other calls never wait for it.
#pragma once

#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "server/render_core.h"
#include "server/scene_field.h"
#include "server/scene_loading.h"
#include "server/scene_manifest.h"
#include "streetsim/v1/scene.pb.h"

namespace streetsim::server {

struct SceneHandle {
  std::string name;
  std::shared_ptr<const SceneManifest> manifest;
  std::shared_ptr<const LoadedScene> scene;
};

class SceneRegistry {
 public:
  SceneRegistry(std::string data_root, std::string job_scenes_dir, RenderCore* core, SceneLoadOptions load = {});
  ~SceneRegistry();

  std::vector<v1::Scene> List();
  absl::StatusOr<v1::Scene> Get(const std::string& name);
  // Starts loading (if not resident) and returns at once, or when done with `wait`.
  absl::StatusOr<v1::Scene> Load(const std::string& name, bool wait, const CancelCheck& cancel);
  absl::Status Unload(const std::string& name);
  // The manifest and the resident scene, loading it first if needed (waits, honouring cancel).
  absl::StatusOr<SceneHandle> Acquire(const std::string& name, const CancelCheck& cancel);
  // Manifest only (no load).
  absl::StatusOr<std::shared_ptr<const SceneManifest>> Manifest(const std::string& name);
  bool Exists(const std::string& name);
  int num_loaded();

 private:
  struct Entry {
    std::string name;
    std::string ply_path;  // a clip set: its clips.json
    bool clip_set = false;
    std::string source;  // "data_root" | "job"
    std::shared_ptr<const SceneManifest> manifest;
    std::string manifest_error;
    v1::SceneState state = v1::SCENE_STATE_AVAILABLE;
    std::string error;
    std::shared_ptr<const LoadedScene> loaded;
    uint64_t generation = 0;  // bumps on every load start / unload
  };

  void RescanLocked();
  Entry* FindLocked(const std::string& name, bool rescan);
  void StartLoadLocked(Entry* entry);
  void FillScene(const Entry& e, bool with_trajectory, v1::Scene* out) const;
  absl::Status WaitLoadedLocked(std::unique_lock<std::mutex>& lock, const std::string& name,
                                const CancelCheck& cancel);

  const std::string data_root_;
  const std::string job_scenes_dir_;
  RenderCore* core_;
  const SceneLoadOptions load_options_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, Entry> entries_;
  std::vector<std::thread> loaders_;
  bool stopping_ = false;
};

}  // namespace streetsim::server
