// The seam where a scene is evaluated at a time. Today every scene is a static Gaussian set
// (StaticSceneField); the dynamic field (HexPlane deformation, scene/field) will implement
// SceneField by evaluating the Gaussians at time_us before rendering.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::server {

// The host-side Gaussians at one time, for renderers outside the engine (the LiDAR renderer
// takes a GaussianStore), with the per-Gaussian LiDAR reflectance when the scene has one.
struct HostScene {
  GaussianStore store;
  std::optional<std::vector<float>> reflectance;  // [N] in [0, 1]; none: 0.5
};

class SceneField {
 public:
  virtual ~SceneField() = default;
  // The device scene to render at `time_us` (valid while this field lives).
  virtual absl::StatusOr<const DeviceScene*> At(int64_t time_us) const = 0;
  // The host Gaussians at `time_us` (LiDAR). The pointer identifies the Gaussian set: the same
  // pointer means the same Gaussians (renderers may keep an upload of it).
  virtual absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t time_us) const = 0;
  virtual size_t num_gaussians() const = 0;
};

class StaticSceneField : public SceneField {
 public:
  StaticSceneField(std::unique_ptr<DeviceScene> scene, std::shared_ptr<const HostScene> host)
      : scene_(std::move(scene)), host_(std::move(host)) {}
  absl::StatusOr<const DeviceScene*> At(int64_t) const override { return scene_.get(); }
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
