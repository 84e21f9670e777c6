#include "server/render_service.h"

#include <optional>

#include "absl/strings/str_cat.h"
#include "server/actor_edits.h"
#include "server/admission.h"
#include "server/request_validation.h"
#include "server/status_mapping.h"
#include "server/time_arithmetic.h"

namespace streetsim::server {
namespace {

enum class PoseKind { kEgo, kSensor, kLog };

struct PosePlan {
  PoseKind kind = PoseKind::kLog;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
};

template <typename Msg>
absl::StatusOr<PosePlan> PlanPose(const Msg& msg, const std::string& field) {
  PosePlan plan;
  if (msg.has_t_world_from_ego()) {
    absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(msg.t_world_from_ego(), field + "T_world_from_ego");
    if (!T.ok()) return T.status();
    plan.kind = PoseKind::kEgo;
    plan.T = *T;
  } else if (msg.has_t_world_from_sensor()) {
    absl::StatusOr<Eigen::Isometry3d> T = PoseFromProto(msg.t_world_from_sensor(), field + "T_world_from_sensor");
    if (!T.ok()) return T.status();
    plan.kind = PoseKind::kSensor;
    plan.T = *T;
  }
  return plan;
}

absl::StatusOr<std::vector<CameraView>> Views(const SceneManifest& manifest,
                                              const std::vector<RigCamera>& cameras,
                                              const PosePlan& plan, int64_t time_us) {
  switch (plan.kind) {
    case PoseKind::kEgo:
      return ViewsAt(cameras, plan.T);
    case PoseKind::kSensor: {
      if (cameras.size() != 1) {
        return absl::InvalidArgumentError("T_world_from_sensor needs exactly one sensor in the request");
      }
      return std::vector<CameraView>{{cameras[0].sensor_id, cameras[0].intrinsics, plan.T}};
    }
    case PoseKind::kLog: {
      std::optional<Eigen::Isometry3d> T = manifest.EgoPoseAt(time_us);
      if (!T) {
        return absl::InvalidArgumentError(
            "no pose given (T_world_from_ego or T_world_from_sensor) and the scene has no ego trajectory");
      }
      return ViewsAt(cameras, *T);
    }
  }
  return absl::InternalError("unreachable");
}

// The sweep's poses: an explicit ego pose is held for the whole sweep; the log's pose follows the
// log's trajectory from time_us to time_us + the sweep duration (a rolling sweep); an explicit
// sensor pose is the LiDAR's own (only when no camera is rendered, else it would be ambiguous).
absl::Status PlaceLidarFor(const SceneManifest& manifest, const PosePlan& plan, int64_t time_us, bool no_cameras,
                           LidarJob* job) {
  switch (plan.kind) {
    case PoseKind::kEgo:
      PlaceLidar(plan.T, plan.T, time_us, job);
      return absl::OkStatus();
    case PoseKind::kSensor:
      if (!no_cameras) {
        return absl::InvalidArgumentError(
            "T_world_from_sensor with a lidar request needs no_cameras (it is then the LiDAR's pose)");
      }
      PlaceLidarAt(plan.T, time_us, job);
      return absl::OkStatus();
    case PoseKind::kLog: {
      std::optional<Eigen::Isometry3d> start = manifest.EgoPoseAt(time_us);
      if (!start) {
        return absl::InvalidArgumentError(
            "no pose given (T_world_from_ego or T_world_from_sensor) and the scene has no ego trajectory");
      }
      absl::StatusOr<int64_t> sweep_end_us = OffsetTimeUs(time_us, 1, job->model.sweep_duration_us);
      if (!sweep_end_us.ok()) return sweep_end_us.status();
      PlaceLidar(*start, *manifest.EgoPoseAt(*sweep_end_us), time_us, job);
      return absl::OkStatus();
    }
  }
  return absl::InternalError("unreachable");
}

absl::Status CheckSize(const google::protobuf::Message& msg, const ServerLimits& limits) {
  if (static_cast<int64_t>(msg.ByteSizeLong()) > limits.max_message_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "response of ", msg.ByteSizeLong(), " bytes exceeds the server's max message size (",
        limits.max_message_bytes, "); ask for PNG/JPEG, fewer sensors or a smaller resolution"));
  }
  return absl::OkStatus();
}

void FillResponse(RenderResult&& r, const std::string& scene, int64_t time_us, v1::RenderResponse* resp) {
  resp->set_scene(scene);
  resp->set_time_us(time_us);
  for (v1::SensorFrame& f : r.frames) *resp->add_frames() = std::move(f);
  if (r.lidar) *resp->mutable_lidar() = std::move(*r.lidar);
  *resp->mutable_timings() = r.timings;
  resp->set_content_digest(r.content_digest);
}

}  // namespace

std::vector<CameraView> ViewsAt(const std::vector<RigCamera>& cameras, const Eigen::Isometry3d& T_world_from_ego) {
  std::vector<CameraView> views;
  for (const RigCamera& c : cameras) {
    views.push_back({c.sensor_id, c.intrinsics, T_world_from_ego * c.T_ego_from_cam});
  }
  return views;
}

grpc::Status RenderServiceImpl::Render(grpc::ServerContext* ctx, const v1::RenderRequest* req,
                                       v1::RenderResponse* resp) {
  absl::Status status = [&]() -> absl::Status {
    if (absl::Status s = deps_->auth.Check(*ctx); !s.ok()) return s;
    if (req->scene().empty()) return absl::InvalidArgumentError("scene is empty");
    absl::StatusOr<v1::OutputSpec> outputs = ValidateOutputs(req->outputs());
    if (!outputs.ok()) return outputs.status();
    absl::StatusOr<PosePlan> plan = PlanPose(*req, "");
    if (!plan.ok()) return plan.status();
    absl::StatusOr<std::shared_ptr<const SceneManifest>> manifest = deps_->scenes->Manifest(req->scene());
    if (!manifest.ok()) return manifest.status();
    if (absl::Status s = CheckTime(**manifest, req->time_us()); !s.ok()) return s;
    if (req->no_cameras() && !req->has_lidar()) {
      return absl::InvalidArgumentError("no_cameras needs a lidar request (nothing to render)");
    }
    absl::StatusOr<std::vector<actors::ActorEdit>> edits = ActorEditsFromProto(req->actor_edits(), "actor_edits");
    if (!edits.ok()) return edits.status();
    std::vector<CameraView> views;
    if (!req->no_cameras()) {
      absl::StatusOr<std::vector<RigCamera>> cams = ResolveSensors(**manifest, req->sensors(), deps_->limits);
      if (!cams.ok()) return cams.status();
      absl::StatusOr<std::vector<CameraView>> v = Views(**manifest, *cams, *plan, req->time_us());
      if (!v.ok()) return v.status();
      views = std::move(*v);
    }
    RenderExtras extras;
    extras.default_background = (*manifest)->background;
    std::optional<LidarJob> lidar;
    if (req->has_lidar()) {
      absl::StatusOr<LidarJob> job = ResolveLidar(req->lidar(), **manifest);
      if (!job.ok()) return job.status();
      lidar = std::move(*job);
      absl::Status placed = PlaceLidarFor(**manifest, *plan, req->time_us(), req->no_cameras(), &*lidar);
      if (!placed.ok()) return placed;
      extras.lidar = &*lidar;
    }
    extras.client = ctx->peer();
    if (absl::Status s = AdmitRender(EstimateRenderCost(views, *outputs, extras.lidar), deps_->limits); !s.ok()) {
      return s;
    }
    const CancelCheck cancel = ContextCancelCheck(ctx);
    absl::StatusOr<SceneHandle> scene = deps_->scenes->Acquire(req->scene(), cancel);
    if (!scene.ok()) return scene.status();
    if (absl::Status s = CheckActorEditsForScene(scene->scene->actors.get(), *edits); !s.ok()) return s;
    std::optional<ActorEditedField> edited;
    if (!edits->empty()) edited.emplace(*scene->scene->field, scene->scene->actors, std::move(*edits));
    const SceneField& field = edited ? static_cast<const SceneField&>(*edited) : *scene->scene->field;
    absl::StatusOr<RenderResult> r = deps_->core->Render(field, req->time_us(), views, *outputs, cancel, extras);
    if (!r.ok()) return r.status();
    FillResponse(std::move(*r), req->scene(), req->time_us(), resp);
    return CheckSize(*resp, deps_->limits);
  }();
  if (!status.ok()) resp->Clear();
  return ToGrpcStatus(status);
}

grpc::Status RenderServiceImpl::RenderTrajectory(grpc::ServerContext* ctx, const v1::RenderTrajectoryRequest* req,
                                                 grpc::ServerWriter<v1::TrajectoryFrame>* writer) {
  absl::Status status = [&]() -> absl::Status {
    if (absl::Status s = deps_->auth.Check(*ctx); !s.ok()) return s;
    if (req->scene().empty()) return absl::InvalidArgumentError("scene is empty");
    if (req->points().empty()) return absl::InvalidArgumentError("points is empty");
    if (req->points_size() > deps_->limits.max_trajectory_poses) {
      return absl::InvalidArgumentError(absl::StrCat("too many points (", req->points_size(), " > ",
                                                     deps_->limits.max_trajectory_poses, ")"));
    }
    absl::StatusOr<v1::OutputSpec> outputs = ValidateOutputs(req->outputs());
    if (!outputs.ok()) return outputs.status();
    absl::StatusOr<std::vector<actors::ActorEdit>> edits = ActorEditsFromProto(req->actor_edits(), "actor_edits");
    if (!edits.ok()) return edits.status();
    absl::StatusOr<std::shared_ptr<const SceneManifest>> manifest = deps_->scenes->Manifest(req->scene());
    if (!manifest.ok()) return manifest.status();
    absl::StatusOr<std::vector<RigCamera>> cams = ResolveSensors(**manifest, req->sensors(), deps_->limits);
    if (!cams.ok()) return cams.status();
    std::optional<LidarJob> lidar_template;
    if (req->has_lidar()) {
      absl::StatusOr<LidarJob> job = ResolveLidar(req->lidar(), **manifest);
      if (!job.ok()) return job.status();
      lidar_template = std::move(*job);
    }
    // Validate every point before rendering any.
    std::vector<std::vector<CameraView>> all_views;
    std::vector<std::optional<LidarJob>> lidar_jobs(req->points_size());
    for (int i = 0; i < req->points_size(); ++i) {
      const v1::TrajectoryPoint& p = req->points(i);
      const std::string field = absl::StrCat("points[", i, "].");
      if (absl::Status s = CheckTime(**manifest, p.time_us()); !s.ok()) {
        return absl::OutOfRangeError(absl::StrCat(field, "time_us: ", s.message()));
      }
      absl::StatusOr<PosePlan> plan = PlanPose(p, field);
      if (!plan.ok()) return plan.status();
      absl::StatusOr<std::vector<CameraView>> views = Views(**manifest, *cams, *plan, p.time_us());
      if (!views.ok()) return absl::InvalidArgumentError(absl::StrCat(field, " ", views.status().message()));
      all_views.push_back(std::move(*views));
      if (lidar_template) {
        lidar_jobs[i] = *lidar_template;
        if (absl::Status s = PlaceLidarFor(**manifest, *plan, p.time_us(), /*no_cameras=*/false, &*lidar_jobs[i]);
            !s.ok()) {
          return absl::InvalidArgumentError(absl::StrCat(field, "lidar: ", s.message()));
        }
      }
    }
    // Every point renders the same sensors and outputs: one point's cost is every point's.
    if (absl::Status s = AdmitRender(EstimateRenderCost(all_views[0], *outputs,
                                                        lidar_jobs[0] ? &*lidar_jobs[0] : nullptr),
                                     deps_->limits);
        !s.ok()) {
      return s;
    }
    const CancelCheck cancel = ContextCancelCheck(ctx);
    absl::StatusOr<SceneHandle> scene = deps_->scenes->Acquire(req->scene(), cancel);
    if (!scene.ok()) return scene.status();
    if (absl::Status s = CheckActorEditsForScene(scene->scene->actors.get(), *edits); !s.ok()) return s;
    std::optional<ActorEditedField> edited;
    if (!edits->empty()) edited.emplace(*scene->scene->field, scene->scene->actors, std::move(*edits));
    const SceneField& field = edited ? static_cast<const SceneField&>(*edited) : *scene->scene->field;
    for (int i = 0; i < req->points_size(); ++i) {
      RenderExtras extras;
      extras.default_background = (*manifest)->background;
      extras.client = ctx->peer();
      if (lidar_jobs[i]) extras.lidar = &*lidar_jobs[i];
      absl::StatusOr<RenderResult> r =
          deps_->core->Render(field, req->points(i).time_us(), all_views[i], *outputs, cancel, extras);
      if (!r.ok()) return r.status();
      v1::TrajectoryFrame frame;
      frame.set_index(i);
      FillResponse(std::move(*r), req->scene(), req->points(i).time_us(), frame.mutable_response());
      if (absl::Status s = CheckSize(frame, deps_->limits); !s.ok()) return s;
      if (!writer->Write(frame)) return absl::CancelledError("client went away");
    }
    return absl::OkStatus();
  }();
  return ToGrpcStatus(status);
}

}  // namespace streetsim::server
