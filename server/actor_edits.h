// Actor edits on the wire (docs/actors.md): converting and checking a request's ActorEdit
// messages, listing a scene's actors, and the scene a render sees with edits applied.
#pragma once

#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "google/protobuf/repeated_field.h"
#include "scene/actors/actor_edits.h"
#include "scene/actors/actor_set.h"
#include "server/scene_field.h"
#include "streetsim/v1/common.pb.h"
#include "streetsim/v1/scene.pb.h"

namespace streetsim::server {

// The edits of a request, checked for shape before any scene is loaded: a kind, at most
// actors::kMaxActorEdits edits, finite unit-quaternion poses at increasing times, a trajectory
// exactly where one belongs. INVALID_ARGUMENT naming `field`[i].
absl::StatusOr<std::vector<actors::ActorEdit>> ActorEditsFromProto(
    const google::protobuf::RepeatedPtrField<v1::ActorEdit>& edits, const std::string& field);

// The edits against the loaded scene's actors (null: the scene has none): INVALID_ARGUMENT for
// an actor it does not have.
absl::Status CheckActorEditsForScene(const actors::ActorSet* set, const std::vector<actors::ActorEdit>& edits);

// Scene.actors (the trajectories only `with_trajectory`).
void ActorsToProto(const actors::ActorSet& set, bool with_trajectory, v1::Scene* out);

// `base` with `edits` applied at every time it is asked for: the base scene's host Gaussians at
// that time, the edited actors' rows taken out and their bodies put back at the edits' poses,
// uploaded for the cameras and handed to the LiDAR. One per render (a session's step, a
// trajectory's point): it keeps the last time's edited scene, so a step's cameras and LiDAR share
// one evaluation and one upload.
class ActorEditedField : public SceneField {
 public:
  ActorEditedField(const SceneField& base, std::shared_ptr<const actors::ActorSet> set,
                   std::vector<actors::ActorEdit> edits);
  absl::StatusOr<const DeviceScene*> At(int64_t time_us, Engine& engine) const override;
  absl::StatusOr<std::shared_ptr<const HostScene>> HostAt(int64_t time_us) const override;
  size_t num_gaussians() const override { return base_.num_gaussians(); }
  FieldStats stats() const override { return base_.stats(); }
  std::optional<Eigen::Vector3f> BackgroundAt(int64_t time_us) const override { return base_.BackgroundAt(time_us); }

 private:
  absl::StatusOr<std::shared_ptr<const HostScene>> EditedAt(int64_t time_us) const;

  const SceneField& base_;
  std::shared_ptr<const actors::ActorSet> set_;
  std::vector<actors::ActorEdit> edits_;
  mutable std::mutex mu_;
  mutable int64_t host_time_us_ = 0;
  mutable std::shared_ptr<const HostScene> host_;
  mutable std::unique_ptr<DeviceScene> device_;
  mutable uint64_t device_generation_ = 0;
};

}  // namespace streetsim::server
