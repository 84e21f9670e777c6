// A clip set (DIR/clips.json + DIR/clip_KKK/, docs/training.md "Clips") served as one scene
// (docs/server.md "Clip sets"): a request at time t is answered by the clip that
// train::PickClip picks for t (the rule of `streetsim render` / `eval`), with that clip's
// Gaussians, field, LiDAR reflectance and learned background. Every clip is loaded exactly as its
// directory is loaded alone (scene_loading.h) and stays resident: device and host memory are the
// sum of the clips'.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "scene/train/clips.h"
#include "server/scene_field.h"
#include "server/scene_loading.h"
#include "server/scene_manifest.h"

namespace streetsim::server {

class ClipSetSceneField : public SceneField {
 public:
  struct Clip {
    std::unique_ptr<SceneField> field;
    std::optional<Eigen::Vector3f> background;  // the clip's train_meta.json; none: the default
  };
  // `clips[k]` serves `set.clips[k]`; the sizes match.
  ClipSetSceneField(train::ClipSet set, std::vector<Clip> clips);

  absl::StatusOr<const DeviceScene*> At(int64_t time_us, Engine& engine) const override;
  absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t time_us) const override;
  absl::StatusOr<std::shared_ptr<const HostScene>> GeometryAt(int64_t time_us) const override;
  size_t num_gaussians() const override;  // sum over the clips
  FieldStats stats() const override;      // sums; has_field when any clip has one; device: the
                                          // clips' when they agree, else "mixed"
  std::optional<Eigen::Vector3f> BackgroundAt(int64_t time_us) const override;

  int ClipAt(int64_t time_us) const { return train::PickClip(set_, time_us); }

 private:
  train::ClipSet set_;
  std::vector<Clip> clips_;
};

// The manifest of the clip set DIR: clip 0's cameras and LiDARs, the union of the clips' time
// ranges (none when a clip has none), the clips' ego trajectories concatenated in time order, no
// background (each clip's comes from ClipSetSceneField::BackgroundAt). Errors name the clip:
// clips.json damage (DataLoss, train::ReadClipSet), a missing clip directory, a clip's manifest
// error, a clip whose camera rig differs from clip 0's, trajectories that overlap.
absl::StatusOr<SceneManifest> ReadClipSetManifest(const std::string& dir);

// Every clip of DIR loaded by LoadSceneFile (a clip that fails fails the set, with its name and
// the single-scene error code), as one LoadedScene: Gaussians summed, bounds the union.
absl::StatusOr<std::shared_ptr<LoadedScene>> LoadClipSet(const std::string& dir, const SceneUploader& upload,
                                                         const SceneLoadOptions& load = {});

}  // namespace streetsim::server
