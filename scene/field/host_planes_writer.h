// The serving form (serving_form.h) written straight into a cpu engine's copy of the scene
// (Engine::WritablePlanes, docs/field.md "Serving form"): a new time is one pass that reads the
// form's tables and writes the moving Gaussians' planes, where the host path evaluates a store and
// then copies its changed rows into the planes (Engine::UpdateSceneRows), twice the memory
// traffic. The same pass writes the host store's geometry, which the LiDAR renders
// (ServingForm::GeometryAt of the same time is then free).
// Not thread-safe: one caller at a time (the server calls it under its scene's lock, on the scene's
// own pool, which the host path uses too: one pool per served scene, not two).
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"

namespace streetsim::field {

inline constexpr char kHostPlanesDevice[] = "cpu";

class HostPlanesWriter : public DeviceSceneWriter {
 public:
  // `engine`, `form` and `pool` must outlive the writer.
  HostPlanesWriter(Engine& engine, ServingForm& form, ThreadPool& pool) : engine_(engine), form_(form), pool_(pool) {}

  // FailedPrecondition when the engine keeps no writable planes of `scene` (a Vulkan engine, the
  // cpu engine in double precision); the form's own errors otherwise.
  absl::Status WriteAt(int64_t time_us, DeviceScene* scene) override;
  std::string device() const override { return kHostPlanesDevice; }

 private:
  Engine& engine_;
  ServingForm& form_;  // writes its store's geometry too (WritePlanesAt)
  ThreadPool& pool_;
};

// For server::DynamicSceneField on a cpu engine: a HostPlanesWriter when `served` is a serving form
// with moving Gaussians and `engine` is a cpu engine, writing on `pool`; null otherwise (the host
// path).
absl::StatusOr<std::unique_ptr<DeviceSceneWriter>> HostPlanesWriterFor(Engine& engine, ServedScene& served,
                                                                        ThreadPool& pool);

}  // namespace streetsim::field
