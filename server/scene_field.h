// The seam where a scene is evaluated at a time: a static Gaussian set (StaticSceneField, below)
// or a dynamic scene deformed by its field.bin, and field_ext.bin for --field extended
// (DynamicSceneField, dynamic_scene_field.h).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::server {

// The host-side Gaussians at one time, for renderers outside the engine (the LiDAR renderer
// takes a GaussianStore), with the per-Gaussian LiDAR reflectance when the scene has one.
// A dynamic scene's HostScene views its field's deformed Gaussians of the last time (no copy),
// valid until the next evaluation, which happens under the engine lock as every read does;
// `generation` changes with every content and is unique across scenes, so a renderer that keeps
// an upload knows when it is stale.
struct HostScene {
  GaussianStore store;                       // owned (a static scene)
  const GaussianStore* view = nullptr;       // or viewed (a dynamic scene's current time)
  std::optional<std::vector<float>> reflectance;  // [N] in [0, 1]; none: 0.5
  uint64_t generation = NewHostSceneGeneration();
  // A dynamic scene: the generation this one follows and what changed since it (a renderer that
  // holds that generation may update just those values); 0 / none: upload everything.
  uint64_t previous_generation = 0;
  std::optional<ParamsChange> change;

  const GaussianStore& gaussians() const { return view ? *view : store; }

  static uint64_t NewHostSceneGeneration() {
    static std::atomic<uint64_t> next{1};
    return next.fetch_add(1);
  }
};

// Engine::Upload for a scene's first upload (RenderCore::Upload: under the engine lock).
using SceneUploader = std::function<absl::StatusOr<std::unique_ptr<DeviceScene>>(const GaussianStore&)>;

// What a scene's field has done (GetScene; tests count evaluations).
struct FieldStats {
  bool has_field = false;
  size_t num_dynamic = 0;         // Gaussians evaluated per timestamp
  int64_t field_evaluations = 0;  // how often the field ran
  std::string device;             // where the field runs now: "cpu" or "vulkan" (empty: no field)
  std::string serving;            // "form" or "exact" (empty: no field); v1::Scene::field_serving
  double form_error_m = 0;        // the serving form's largest position error at its check samples
};

class SceneField {
 public:
  virtual ~SceneField() = default;
  // The device scene to render at `time_us` (valid until the next At of this field). Called by
  // RenderCore with the engine lock held: `engine` updates the device copy when the time changes.
  virtual absl::StatusOr<const DeviceScene*> At(int64_t time_us, Engine& engine) const = 0;
  // The host Gaussians at `time_us` (LiDAR). The pointer identifies the Gaussian set: the same
  // pointer means the same Gaussians (renderers may keep an upload of it).
  virtual absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t time_us) const = 0;
  // What a LiDAR sweep reads: HostAt's Gaussians with their geometry (positions, scales, rotations,
  // opacities) at `time_us` and their colours possibly another time's (a dynamic scene evaluates
  // only what the sweep needs). The default is HostAt.
  virtual absl::StatusOr<std::shared_ptr<const HostScene>> GeometryAt(int64_t time_us) const {
    return HostAt(time_us);
  }
  virtual size_t num_gaussians() const = 0;
  virtual FieldStats stats() const { return {}; }
  // The learned background at `time_us` when it depends on the time (a clip set: each clip's
  // own); nullopt: the manifest's (RenderExtras::default_background). A request's background_rgb
  // wins over both.
  virtual std::optional<Eigen::Vector3f> BackgroundAt(int64_t /*time_us*/) const { return std::nullopt; }
};

class StaticSceneField : public SceneField {
 public:
  StaticSceneField(std::unique_ptr<DeviceScene> scene, std::shared_ptr<const HostScene> host)
      : scene_(std::move(scene)), host_(std::move(host)) {}
  absl::StatusOr<const DeviceScene*> At(int64_t, Engine&) const override { return scene_.get(); }
  absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t) const override {
    if (!host_) return absl::FailedPreconditionError("this scene keeps no host copy (LiDAR unavailable)");
    return host_;
  }
  size_t num_gaussians() const override { return scene_->size(); }

 private:
  std::unique_ptr<DeviceScene> scene_;
  std::shared_ptr<const HostScene> host_;
};

}  // namespace streetsim::server
