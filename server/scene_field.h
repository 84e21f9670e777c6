// The seam where a scene is evaluated at a time. Today every scene is a static Gaussian set
// (StaticSceneField); the dynamic field (HexPlane deformation, scene/field) will implement
// SceneField by evaluating the Gaussians at time_us before rendering.
#pragma once

#include <cstdint>
#include <memory>

#include "absl/status/statusor.h"
#include "render/engine.h"

namespace streetsim::server {

class SceneField {
 public:
  virtual ~SceneField() = default;
  // The device scene to render at `time_us` (valid while this field lives).
  virtual absl::StatusOr<const DeviceScene*> At(int64_t time_us) const = 0;
  virtual size_t num_gaussians() const = 0;
};

class StaticSceneField : public SceneField {
 public:
  explicit StaticSceneField(std::unique_ptr<DeviceScene> scene) : scene_(std::move(scene)) {}
  absl::StatusOr<const DeviceScene*> At(int64_t) const override { return scene_.get(); }
  size_t num_gaussians() const override { return scene_->size(); }

 private:
  std::unique_ptr<DeviceScene> scene_;
};

}  // namespace streetsim::server
