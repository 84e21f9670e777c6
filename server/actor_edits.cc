#include "server/actor_edits.h"

#include "absl/strings/str_cat.h"
#include "server/proto_convert.h"

namespace streetsim::server {

absl::StatusOr<std::vector<actors::ActorEdit>> ActorEditsFromProto(
    const google::protobuf::RepeatedPtrField<v1::ActorEdit>& edits, const std::string& field) {
  if (static_cast<size_t>(edits.size()) > actors::kMaxActorEdits) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": ", edits.size(), " actor edits; at most ", actors::kMaxActorEdits, " per request"));
  }
  std::vector<actors::ActorEdit> out;
  for (int i = 0; i < edits.size(); ++i) {
    const v1::ActorEdit& e = edits[i];
    const std::string name = absl::StrCat(field, "[", i, "]");
    actors::ActorEdit edit;
    edit.actor_id = e.actor_id();
    switch (e.kind()) {
      case v1::ACTOR_EDIT_REMOVE: edit.kind = actors::ActorEdit::Kind::kRemove; break;
      case v1::ACTOR_EDIT_MOVE: edit.kind = actors::ActorEdit::Kind::kMove; break;
      case v1::ACTOR_EDIT_INSERT: edit.kind = actors::ActorEdit::Kind::kInsert; break;
      default:
        return absl::InvalidArgumentError(absl::StrCat(name, ".kind: REMOVE, MOVE or INSERT, not ", e.kind()));
    }
    if (edit.kind == actors::ActorEdit::Kind::kRemove && e.trajectory_size() > 0) {
      return absl::InvalidArgumentError(absl::StrCat(name, ": a removal takes no trajectory"));
    }
    if (edit.kind != actors::ActorEdit::Kind::kRemove &&
        (e.trajectory().empty() || static_cast<size_t>(e.trajectory_size()) > actors::kMaxEditPoses)) {
      return absl::InvalidArgumentError(absl::StrCat(name, ".trajectory: 1 to ", actors::kMaxEditPoses,
                                                     " poses, not ", e.trajectory_size()));
    }
    for (int k = 0; k < e.trajectory_size(); ++k) {
      const std::string pose_field = absl::StrCat(name, ".trajectory[", k, "]");
      if (!e.trajectory(k).has_t_world_from_actor()) {
        return absl::InvalidArgumentError(absl::StrCat(pose_field, ".T_world_from_actor is missing"));
      }
      absl::StatusOr<Eigen::Isometry3d> T =
          PoseFromProto(e.trajectory(k).t_world_from_actor(), pose_field + ".T_world_from_actor");
      if (!T.ok()) return T.status();
      if (k > 0 && e.trajectory(k).time_us() <= e.trajectory(k - 1).time_us()) {
        return absl::InvalidArgumentError(absl::StrCat(pose_field, ".time_us does not increase"));
      }
      edit.trajectory.push_back({e.trajectory(k).time_us(), *T});
    }
    out.push_back(std::move(edit));
  }
  return out;
}

absl::Status CheckActorEditsForScene(const actors::ActorSet* set, const std::vector<actors::ActorEdit>& edits) {
  if (edits.empty()) return absl::OkStatus();
  if (set == nullptr) {
    return absl::InvalidArgumentError("actor_edits: the scene has no actors (docs/actors.md: streetsim actors extract)");
  }
  return actors::ValidateActorEdits(*set, edits);
}

void ActorsToProto(const actors::ActorSet& set, bool with_trajectory, v1::Scene* out) {
  for (const actors::Actor& a : set.actors) {
    v1::Actor* p = out->add_actors();
    p->set_actor_id(a.id);
    p->set_start_time_us(a.start_time_us());
    p->set_end_time_us(a.end_time_us());
    p->mutable_half_extent_m()->set_x(a.half_extent_m.x());
    p->mutable_half_extent_m()->set_y(a.half_extent_m.y());
    p->mutable_half_extent_m()->set_z(a.half_extent_m.z());
    p->set_num_gaussians(a.body_rows.size());
    p->set_num_ghost_gaussians(a.ghost_rows.size());
    if (!with_trajectory) continue;
    for (const actors::TimedPose& pose : a.trajectory) {
      v1::ActorPose* q = p->add_trajectory();
      q->set_time_us(pose.time_us);
      PoseToProto(pose.T_world_from_actor, q->mutable_t_world_from_actor());
    }
  }
}

ActorEditedField::ActorEditedField(const SceneField& base, std::shared_ptr<const actors::ActorSet> set,
                                   std::vector<actors::ActorEdit> edits)
    : base_(base), set_(std::move(set)), edits_(std::move(edits)) {}

absl::StatusOr<std::shared_ptr<const HostScene>> ActorEditedField::EditedAt(int64_t time_us) const {
  if (host_ && host_time_us_ == time_us) return host_;
  absl::StatusOr<std::shared_ptr<const HostScene>> base = base_.HostAt(time_us);
  if (!base.ok()) return base.status();
  const std::vector<float>* reflectance = (*base)->reflectance ? &*(*base)->reflectance : nullptr;
  actors::EditedScene edited = actors::ApplyActorEdits((*base)->gaussians(), reflectance, *set_, edits_, time_us);
  auto host = std::make_shared<HostScene>();
  host->store = std::move(edited.gaussians);
  host->reflectance = std::move(edited.reflectance);
  host_ = std::move(host);
  host_time_us_ = time_us;
  return host_;
}

absl::StatusOr<const DeviceScene*> ActorEditedField::At(int64_t time_us, Engine& engine) const {
  std::lock_guard<std::mutex> lock(mu_);
  absl::StatusOr<std::shared_ptr<const HostScene>> host = EditedAt(time_us);
  if (!host.ok()) return host.status();
  if (!device_ || device_generation_ != (*host)->generation) {
    absl::StatusOr<std::unique_ptr<DeviceScene>> device = engine.Upload((*host)->gaussians());
    if (!device.ok()) return device.status();
    device_ = std::move(*device);
    device_generation_ = (*host)->generation;
  }
  return device_.get();
}

absl::StatusOr<std::shared_ptr<const HostScene>> ActorEditedField::HostAt(int64_t time_us) const {
  std::lock_guard<std::mutex> lock(mu_);
  return EditedAt(time_us);
}

}  // namespace streetsim::server
