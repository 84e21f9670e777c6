// How one scene directory (or bare .ply) becomes a manifest and a resident SceneField: shared by
// the registry's single scenes and by each clip of a clip set (clip_set_scene_field.h), so a clip
// served inside its set is loaded exactly as the clip directory served alone.
#pragma once

#include <memory>
#include <string>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "scene/train/dynamic_stage.h"
#include "scene/actors/actor_set.h"
#include "server/scene_field.h"
#include "server/scene_manifest.h"

namespace streetsim::server {

struct LoadedScene {
  std::unique_ptr<SceneField> field;
  size_t num_gaussians = 0;
  Eigen::Vector3d min_m = Eigen::Vector3d::Zero(), max_m = Eigen::Vector3d::Zero();
  double load_time_s = 0;  // PLY, field.bin, static analysis and upload
  // DIR/actors.json (docs/actors.md); null when the scene has none.
  std::shared_ptr<const actors::ActorSet> actors;
};

struct SceneLoadOptions {
  // Where a dynamic scene's field runs, resolved (kCpu or kVulkan: Server::Start resolves the
  // server's --field-device against its engine, train::ResolveFieldDevice). kVulkan falls back to
  // the cpu with a warning when the device fails (render/vulkan/field/vulkan_serving.h).
  train::FieldDevice field_device = train::FieldDevice::kCpu;
  field::StaticSkipOptions static_skip;  // ServerOptions::static_skip
  // false (the default): a dynamic scene is served through its serving form (cached in
  // DIR/field.serving, scene/field/serving_form.h); true: the field's network per timestamp.
  bool exact_field = false;
  field::ServingFormOptions serving_form;
};

// The manifest of a scene: `manifest_path` (DIR/scene.json; absent: the default rig; empty: a bare
// .ply, the default rig) plus the learned background of DIR/train_meta.json when present.
// Errors: a malformed scene.json (InvalidArgument) or train_meta.json (DataLoss), naming the file.
absl::StatusOr<SceneManifest> ReadSceneDirManifest(const std::string& manifest_path);

// Reads `ply_path` (with its LiDAR reflectance), and for DIR/scene.ply with DIR/field.bin the
// field (a DynamicSceneField; with DIR/field_ext.bin beside it the extended field of a --field
// extended run), else a StaticSceneField; uploads through `upload`.
// Errors: a PLY, field.bin or field_ext.bin that cannot be read, or a field_ext.bin of another
// field.bin (DataLoss naming the file), upload failures.
absl::StatusOr<std::shared_ptr<LoadedScene>> LoadSceneFile(const std::string& ply_path, const SceneUploader& upload,
                                                           const SceneLoadOptions& load = {});

}  // namespace streetsim::server
