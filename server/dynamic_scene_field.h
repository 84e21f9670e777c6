// A dynamic scene served at the request's time (docs/server.md "Dynamic scenes"): a
// field::ServedScene (scene_loading.cc makes it: the serving form of DIR/field.bin, or the exact
// field through field::ServingField / field::ExtServingField, possibly on a Vulkan device),
// evaluated once per new timestamp. The Gaussians of the last timestamp are kept on the device and
// on the host, so every camera and the LiDAR of one step share one evaluation, and a new time
// updates only what the served scene changes (ServedScene::changes).
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/static_skip.h"
#include "server/scene_field.h"

namespace streetsim::server {

// Makes what writes a serving form straight into an engine's copy of the scene
// (field::DeviceWriterFor for a Vulkan engine, field::HostPlanesWriterFor for the cpu engine). An
// error or a null writer keeps the form on the host (evaluate, then update the engine's rows). The
// pool is the scene's own (a writer on the host uses it under the scene's lock).
using DeviceWriterMaker = std::function<absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>>(
    Engine&, field::ServedScene&, ThreadPool&)>;

class DynamicSceneField : public SceneField {
 public:
  // Evaluates `served` at its start and uploads that through `upload`. make_writer is called at
  // the first At; its writer then writes each new time into the engine's copy, and the host
  // evaluates only for HostAt and GeometryAt. A writer that fails is dropped with a warning: the
  // host evaluates and uploads from then on.
  static absl::StatusOr<std::unique_ptr<DynamicSceneField>> Create(std::unique_ptr<field::ServedScene> served,
                                                                   std::optional<std::vector<float>> reflectance,
                                                                   const SceneUploader& upload,
                                                                   DeviceWriterMaker make_writer = {});

  absl::StatusOr<const DeviceScene*> At(int64_t time_us, Engine& engine) const override;
  absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t time_us) const override;
  absl::StatusOr<std::shared_ptr<const HostScene>> GeometryAt(int64_t time_us) const override;
  size_t num_gaussians() const override { return num_gaussians_; }
  FieldStats stats() const override;

 private:
  DynamicSceneField() = default;
  // The deformed store at time_us, all of it or its geometry (mu_ held).
  absl::StatusOr<const GaussianStore*> EvaluateLocked(int64_t time_us, bool geometry_only = false) const;
  absl::StatusOr<std::shared_ptr<const HostScene>> HostLocked(int64_t time_us, bool geometry_only) const;
  // A time evaluated, by the host or the writer: counted once however many parts of it are
  // evaluated (the engine's copy, the LiDAR's geometry), as GetScene's field_evaluations.
  void CountLocked(int64_t time_us) const;
  int64_t ClampedLocked(int64_t time_us) const;  // into serving_'s time range
  // The device copy at time_us through writer_ (mu_ held). False: no writer (none could be made,
  // or it failed now: a warning, and the host path from now on).
  bool WriteOnDeviceLocked(int64_t time_us, Engine& engine) const;

  mutable std::mutex mu_;
  mutable std::unique_ptr<ThreadPool> pool_;
  mutable std::unique_ptr<field::ServedScene> serving_;
  mutable std::unique_ptr<DeviceScene> device_;
  mutable int64_t device_evaluation_ = 0;  // serving_'s evaluation count the device copy holds (0: baked;
                                           // -1: unknown, e.g. written by writer_)
  mutable DeviceWriterMaker make_writer_;  // Create's, until the first At calls it
  mutable std::unique_ptr<field::DeviceSceneWriter> writer_;
  mutable std::optional<int64_t> writer_time_us_;  // the time writer_ last wrote into the device copy
  mutable int64_t timestamps_ = 0;              // CountLocked's count
  mutable std::optional<int64_t> counted_time_us_;  // the time it counted last
  mutable std::shared_ptr<HostScene> host_;  // views the serving field's current Gaussians (HostScene)
  mutable int64_t host_evaluation_ = -1;
  std::optional<std::vector<float>> reflectance_;
  size_t num_gaussians_ = 0;
  size_t num_dynamic_ = 0;
  // A copy of timestamps_ that GetScene reads without waiting for an evaluation in progress.
  mutable std::atomic<int64_t> evaluations_{0};
  // Whether serving_ still evaluates on its device (GetScene reads it the same way).
  std::string device_name_ = "cpu";
  mutable std::atomic<bool> on_device_{false};
  mutable std::atomic<bool> on_writer_{false};  // writer_ writes the device copy (GetScene: its device)
  mutable std::string writer_device_;           // writer_'s device(), set once before on_writer_
};

}  // namespace streetsim::server
