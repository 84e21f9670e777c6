#include "server/session_manager.h"

#include <optional>
#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/actor_edits.h"
#include "server/admission.h"
#include "server/digest.h"
#include "server/echo.h"
#include "server/render_service.h"
#include "server/replica.h"
#include "server/request_identity.h"
#include "server/request_validation.h"
#include "server/time_arithmetic.h"

namespace streetsim::server {

constexpr int64_t kDefaultStepDtUs = 100000;

void SessionManager::Renew(Session& s) {
  s.lease_expiry = std::chrono::steady_clock::now() + std::chrono::milliseconds(deps_->limits.session_lease_ms);
}

void SessionManager::PurgeExpiredLocked() {
  const auto now = std::chrono::steady_clock::now();
  for (auto it = sessions_.begin(); it != sessions_.end();) {
    Session& s = *it->second;
    std::unique_lock<std::mutex> step(s.step_mu, std::try_to_lock);  // a running step keeps it
    bool expired = false;
    if (step.owns_lock()) {
      std::lock_guard<std::mutex> l(s.mu);
      expired = s.lease_expiry < now;
    }
    if (expired) {
      for (auto r = by_request_id_.begin(); r != by_request_id_.end();) {
        r = r->second == it->first ? by_request_id_.erase(r) : std::next(r);
      }
      it = sessions_.erase(it);
    } else {
      ++it;
    }
  }
}

std::shared_ptr<SessionManager::Session> SessionManager::FindLocked(const std::string& id) {
  PurgeExpiredLocked();
  auto it = sessions_.find(id);
  return it == sessions_.end() ? nullptr : it->second;
}

std::string SessionManager::NewIdLocked() {
  static thread_local std::mt19937_64 rng(std::random_device{}());
  return ReplicaScopedId(deps_->replica, absl::StrFormat("s-%d-%08x", next_id_++, static_cast<uint32_t>(rng())));
}

int SessionManager::size() {
  std::lock_guard<std::mutex> lock(mu_);
  PurgeExpiredLocked();
  return static_cast<int>(sessions_.size());
}

v1::Session SessionManager::Describe(Session& s) {
  v1::Session out;
  out.set_session_id(s.id);
  out.set_scene(s.scene);
  out.set_start_time_us(s.start_time_us);
  out.set_step_dt_us(s.step_dt_us);
  out.set_seed(s.seed);
  out.set_forked_from(s.forked_from);
  for (const RigCamera& c : s.cameras) {
    v1::CameraSpec* spec = out.mutable_rig()->add_cameras();
    spec->set_sensor_id(c.sensor_id);
    IntrinsicsToProto(c.intrinsics, spec->mutable_intrinsics());
    PoseToProto(c.T_ego_from_cam, spec->mutable_t_ego_from_sensor());
  }
  std::lock_guard<std::mutex> l(s.mu);
  out.set_last_step_index(s.state.last_step_index);
  out.set_time_us(s.state.time_us);
  PoseToProto(s.state.T_world_from_ego, out.mutable_t_world_from_ego());
  out.set_lease_expires_in_ms(std::chrono::duration_cast<std::chrono::milliseconds>(
                                  s.lease_expiry - std::chrono::steady_clock::now()).count());
  return out;
}

absl::Status SessionManager::UnknownSession(const std::string& id) const {
  const std::string_view owner = ReplicaOfId(id);
  if (!owner.empty() && owner != deps_->replica) {
    return absl::NotFoundError(absl::StrCat("session ", Echo(id), " belongs to replica ", Echo(std::string(owner)),
                                            ", not this one (", Echo(deps_->replica),
                                            "): send a session's calls to the replica that created it"));
  }
  return absl::NotFoundError(absl::StrCat("unknown or expired session ", Echo(id)));
}

absl::StatusOr<v1::Session> SessionManager::Create(const v1::CreateSessionRequest& req) {
  if (deps_->draining) return absl::UnavailableError("server is shutting down");
  if (req.scene().empty()) return absl::InvalidArgumentError("scene is empty");
  if (req.step_dt_us() < 0) return absl::InvalidArgumentError("step_dt_us must be > 0");
  absl::StatusOr<v1::OutputSpec> outputs = ValidateOutputs(req.outputs());
  if (!outputs.ok()) return outputs.status();
  absl::StatusOr<std::shared_ptr<const SceneManifest>> manifest = deps_->scenes->Manifest(req.scene());
  if (!manifest.ok()) return manifest.status();
  absl::StatusOr<std::vector<RigCamera>> cams = ResolveSensors(**manifest, req.sensors(), deps_->limits);
  if (!cams.ok()) return cams.status();
  std::optional<LidarJob> lidar;
  if (req.has_lidar()) {
    absl::StatusOr<LidarJob> job = ResolveLidar(req.lidar(), **manifest);
    if (!job.ok()) return job.status();
    lidar = std::move(*job);
  }
  absl::StatusOr<std::vector<actors::ActorEdit>> edits = ActorEditsFromProto(req.actor_edits(), "actor_edits");
  if (!edits.ok()) return edits.status();
  // A session whose every step would be refused for its size is refused now.
  if (absl::Status s = AdmitRender(EstimateRenderCost(ViewsAt(*cams, Eigen::Isometry3d::Identity()), *outputs,
                                                      lidar ? &*lidar : nullptr),
                                   deps_->limits);
      !s.ok()) {
    return s;
  }
  int64_t start = req.start_time_us();
  if (start == 0 && (*manifest)->has_time_range) start = (*manifest)->start_us;
  if (absl::Status s = CheckTime(**manifest, start); !s.ok()) return s;
  Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
  if (req.has_initial_t_world_from_ego()) {
    absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(req.initial_t_world_from_ego(), "initial_T_world_from_ego");
    if (!T.ok()) return T.status();
    ego = *T;
  } else if (auto T = (*manifest)->EgoPoseAt(start)) {
    ego = *T;
  }

  std::lock_guard<std::mutex> lock(mu_);
  PurgeExpiredLocked();
  if (!req.request_id().empty()) {
    auto it = by_request_id_.find(req.request_id());
    if (it != by_request_id_.end() && sessions_.count(it->second)) {
      Session& existing = *sessions_[it->second];
      if (existing.request_fingerprint != RequestFingerprint(req)) return RequestIdReused(req.request_id(), "session");
      return Describe(existing);
    }
  }
  if (static_cast<int>(sessions_.size()) >= deps_->limits.max_sessions) {
    return absl::ResourceExhaustedError(absl::StrCat("session limit reached (", deps_->limits.max_sessions,
                                                     "); close a session or wait for a lease to expire"));
  }
  auto s = std::make_shared<Session>();
  s->id = NewIdLocked();
  s->scene = req.scene();
  s->manifest = *manifest;
  s->cameras = std::move(*cams);
  s->outputs = *outputs;
  if (req.has_lidar()) s->lidar = req.lidar();
  s->start_time_us = start;
  s->step_dt_us = req.step_dt_us() == 0 ? kDefaultStepDtUs : req.step_dt_us();
  s->seed = req.seed();
  s->state.time_us = start;
  s->state.T_world_from_ego = ego;
  s->state.actor_edits = std::move(*edits);
  Renew(*s);
  sessions_[s->id] = s;
  if (!req.request_id().empty()) {
    by_request_id_[req.request_id()] = s->id;
    s->request_fingerprint = RequestFingerprint(req);
  }
  return Describe(*s);
}

absl::StatusOr<v1::Session> SessionManager::Get(const std::string& id) {
  std::shared_ptr<Session> s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    s = FindLocked(id);
  }
  if (!s) return UnknownSession(id);
  {
    std::lock_guard<std::mutex> l(s->mu);
    Renew(*s);
  }
  return Describe(*s);
}

std::vector<v1::Session> SessionManager::List() {
  std::vector<std::shared_ptr<Session>> all;
  {
    std::lock_guard<std::mutex> lock(mu_);
    PurgeExpiredLocked();
    for (auto& [id, s] : sessions_) all.push_back(s);
  }
  std::vector<v1::Session> out;
  for (auto& s : all) out.push_back(Describe(*s));
  return out;
}

absl::Status SessionManager::Close(const std::string& id) {
  std::lock_guard<std::mutex> lock(mu_);
  if (!FindLocked(id)) return UnknownSession(id);
  sessions_.erase(id);
  for (auto r = by_request_id_.begin(); r != by_request_id_.end();) {
    r = r->second == id ? by_request_id_.erase(r) : std::next(r);
  }
  return absl::OkStatus();
}

absl::StatusOr<v1::Session> SessionManager::Fork(const std::string& id) {
  if (deps_->draining) return absl::UnavailableError("server is shutting down");
  std::lock_guard<std::mutex> lock(mu_);
  std::shared_ptr<Session> src = FindLocked(id);
  if (!src) return UnknownSession(id);
  if (static_cast<int>(sessions_.size()) >= deps_->limits.max_sessions) {
    return absl::ResourceExhaustedError(absl::StrCat("session limit reached (", deps_->limits.max_sessions, ")"));
  }
  auto s = std::make_shared<Session>();
  s->id = NewIdLocked();
  s->scene = src->scene;
  s->manifest = src->manifest;
  s->cameras = src->cameras;
  s->outputs = src->outputs;
  s->lidar = src->lidar;
  s->start_time_us = src->start_time_us;
  s->step_dt_us = src->step_dt_us;
  s->seed = src->seed;
  s->forked_from = src->id;
  {
    std::lock_guard<std::mutex> l(src->mu);  // committed state only: a step in flight is not seen
    s->state = src->state;
    Renew(*src);
  }
  Renew(*s);
  sessions_[s->id] = s;
  return Describe(*s);
}

absl::StatusOr<std::shared_ptr<const v1::StepResponse>> SessionManager::Step(const v1::StepRequest& req,
                                                                             const CancelCheck& cancel) {
  std::shared_ptr<Session> s;
  {
    std::lock_guard<std::mutex> lock(mu_);
    s = FindLocked(req.session_id());
  }
  if (!s) return UnknownSession(req.session_id());
  std::unique_lock<std::mutex> step(s->step_mu, std::try_to_lock);
  if (!step.owns_lock()) {
    return absl::AbortedError("another step of this session is in flight (one writer per session)");
  }
  Committed state;
  {
    std::lock_guard<std::mutex> l(s->mu);
    Renew(*s);
    state = s->state;
  }
  if (req.step_index() == state.last_step_index && state.last_response) return state.last_response;
  if (req.step_index() != state.last_step_index + 1) {
    return absl::FailedPreconditionError(absl::StrCat("step_index ", req.step_index(), " but the session expects ",
                                                      state.last_step_index + 1, " (or ", state.last_step_index,
                                                      " to repeat the last step)"));
  }
  absl::StatusOr<int64_t> step_time_us = OffsetTimeUs(s->start_time_us, req.step_index(), s->step_dt_us);
  if (!step_time_us.ok()) return step_time_us.status();
  const int64_t time_us = *step_time_us;
  if (absl::Status st = CheckTime(*s->manifest, time_us); !st.ok()) return st;
  v1::OutputSpec outputs = s->outputs;
  if (req.has_outputs()) {
    absl::StatusOr<v1::OutputSpec> o = ValidateOutputs(req.outputs());
    if (!o.ok()) return o.status();
    outputs = *o;
  }
  std::optional<LidarJob> lidar;
  if (req.has_lidar() || s->lidar) {
    absl::StatusOr<LidarJob> job = ResolveLidar(req.has_lidar() ? req.lidar() : *s->lidar, *s->manifest);
    if (!job.ok()) return job.status();
    lidar = std::move(*job);
  }
  Eigen::Isometry3d ego = state.T_world_from_ego;
  Eigen::Isometry3d ego_sweep_end = ego;  // held still unless a trajectory says otherwise
  if (req.has_t_world_from_ego()) {
    absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(req.t_world_from_ego(), "T_world_from_ego");
    if (!T.ok()) return T.status();
    ego = *T;
  } else if (req.has_trajectory()) {
    const auto& poses = req.trajectory().poses();
    if (poses.empty()) return absl::InvalidArgumentError("trajectory.poses is empty");
    if (poses.size() > deps_->limits.max_trajectory_poses) {
      return absl::InvalidArgumentError("trajectory has too many poses");
    }
    std::vector<TimedEgoPose> traj;
    for (int i = 0; i < poses.size(); ++i) {
      absl::StatusOr<Eigen::Isometry3d> T =
          PoseFromProto(poses[i].t_world_from_ego(), absl::StrCat("trajectory.poses[", i, "].T_world_from_ego"));
      if (!T.ok()) return T.status();
      if (!traj.empty() && poses[i].time_us() <= traj.back().time_us) {
        return absl::InvalidArgumentError("trajectory.poses times must strictly increase");
      }
      traj.push_back({poses[i].time_us(), *T});
    }
    ego = InterpolateTrajectory(traj, time_us);
    if (lidar) {
      absl::StatusOr<int64_t> sweep_end_us = OffsetTimeUs(time_us, 1, lidar->model.sweep_duration_us);
      if (!sweep_end_us.ok()) return sweep_end_us.status();
      ego_sweep_end = InterpolateTrajectory(traj, *sweep_end_us);
    }
  }
  if (!req.has_trajectory()) ego_sweep_end = ego;
  RenderExtras extras;
  extras.default_background = s->manifest->background;
  extras.client = s->id;
  if (lidar) {
    PlaceLidar(ego, ego_sweep_end, time_us, &*lidar);
    extras.lidar = &*lidar;
  }
  const std::vector<CameraView> views = ViewsAt(s->cameras, ego);
  if (absl::Status st = AdmitRender(EstimateRenderCost(views, outputs, extras.lidar), deps_->limits); !st.ok()) {
    return st;
  }
  std::vector<actors::ActorEdit> actor_edits = state.actor_edits;
  if (req.has_actor_edits()) {
    absl::StatusOr<std::vector<actors::ActorEdit>> e = ActorEditsFromProto(req.actor_edits().edits(), "actor_edits.edits");
    if (!e.ok()) return e.status();
    actor_edits = std::move(*e);
  }
  absl::StatusOr<SceneHandle> scene = deps_->scenes->Acquire(s->scene, cancel);
  if (!scene.ok()) return scene.status();
  if (absl::Status st = CheckActorEditsForScene(scene->scene->actors.get(), actor_edits); !st.ok()) return st;
  std::optional<ActorEditedField> edited;
  if (!actor_edits.empty()) edited.emplace(*scene->scene->field, scene->scene->actors, actor_edits);
  const SceneField& field = edited ? static_cast<const SceneField&>(*edited) : *scene->scene->field;
  absl::StatusOr<RenderResult> r = deps_->core->Render(field, time_us, views, outputs, cancel, extras);
  if (!r.ok()) return r.status();
  auto resp = std::make_shared<v1::StepResponse>();
  resp->set_session_id(s->id);
  resp->set_step_index(req.step_index());
  resp->set_time_us(time_us);
  PoseToProto(ego, resp->mutable_t_world_from_ego());
  for (v1::SensorFrame& f : r->frames) *resp->add_frames() = std::move(f);
  if (r->lidar) *resp->mutable_lidar() = std::move(*r->lidar);
  *resp->mutable_timings() = r->timings;
  resp->set_content_digest(r->content_digest);
  if (static_cast<int64_t>(resp->ByteSizeLong()) > deps_->limits.max_message_bytes) {
    return absl::ResourceExhaustedError("step response exceeds the server's max message size; ask for PNG/JPEG");
  }
  // Last chance to give up: after this the step is committed.
  if (absl::Status st = cancel(); !st.ok()) return st;
  {
    std::lock_guard<std::mutex> l(s->mu);
    s->state.last_step_index = req.step_index();
    s->state.time_us = time_us;
    s->state.T_world_from_ego = ego;
    s->state.last_response = resp;
    s->state.actor_edits = std::move(actor_edits);
    Renew(*s);
  }
  return std::shared_ptr<const v1::StepResponse>(resp);
}

}  // namespace streetsim::server
