#include "server/info_and_scene_services.h"

#include <unistd.h>

#include <fstream>

#include "server/job_runner.h"
#include "server/session_manager.h"
#include "server/status_mapping.h"

#ifndef STREETSIM_VERSION
#define STREETSIM_VERSION "unknown"
#endif

namespace streetsim::server {

#define STREETSIM_AUTH(ctx)                                                \
  if (absl::Status _s = deps_->auth.Check(*(ctx)); !_s.ok()) return ToGrpcStatus(_s)

int64_t CurrentRssBytes() {
  std::ifstream in("/proc/self/statm");
  int64_t pages_total = 0, pages_rss = 0;
  in >> pages_total >> pages_rss;
  return pages_rss * sysconf(_SC_PAGESIZE);
}

grpc::Status ServerInfoServiceImpl::GetServerInfo(grpc::ServerContext* ctx, const v1::GetServerInfoRequest*,
                                                  v1::ServerInfo* resp) {
  STREETSIM_AUTH(ctx);
  resp->set_api_version(kApiVersion);
  resp->set_build_version(STREETSIM_VERSION);
  resp->set_backend(deps_->core->backend_name());
  resp->set_device(deps_->core->device_name());
  const ServerLimits& l = deps_->limits;
  v1::Limits* lim = resp->mutable_limits();
  lim->set_max_image_width(l.max_image_width);
  lim->set_max_image_height(l.max_image_height);
  lim->set_max_message_bytes(l.max_message_bytes);
  lim->set_max_sessions(l.max_sessions);
  lim->set_max_queued_renders(l.max_queued_renders);
  lim->set_max_trajectory_poses(l.max_trajectory_poses);
  lim->set_max_sensors_per_request(l.max_sensors_per_request);
  lim->set_session_lease_s(l.session_lease_ms / 1000);
  lim->set_max_concurrent_jobs(l.max_concurrent_jobs);
  lim->set_max_request_pixels(l.max_request_pixels);
  lim->set_max_lidar_rays(l.max_lidar_rays);
  lim->set_max_queued_renders_per_client(l.max_queued_renders_per_client);
  v1::Load* load = resp->mutable_load();
  load->set_sessions(deps_->sessions->size());
  load->set_renders_in_flight(deps_->core->in_flight());
  load->set_scenes_loaded(deps_->scenes->num_loaded());
  load->set_jobs_running(deps_->jobs->running());
  load->set_server_rss_bytes(CurrentRssBytes());
  // What this server does now, so a client can check before it asks.
  for (const char* c : {"render", "render_trajectory", "sessions", "drive", "fork_session", "lidar",
                        "dynamic_scenes", "extended_field", "clip_sets", "encodings:raw,png,jpeg", "depth:f32,png16",
                        "camera:pinhole"}) {
    resp->add_capabilities(c);
  }
  // Whether a training job trains (a `streetsim train` beside the server) or only initialises.
  resp->add_capabilities(deps_->jobs != nullptr && deps_->jobs->TrainAvailable() ? "training:train" : "training:init-only");
  resp->set_auth_required(deps_->auth.enabled());
  resp->set_tls(deps_->tls);
  return grpc::Status::OK;
}

grpc::Status SceneServiceImpl::ListScenes(grpc::ServerContext* ctx, const v1::ListScenesRequest*,
                                          v1::ListScenesResponse* resp) {
  STREETSIM_AUTH(ctx);
  for (v1::Scene& s : deps_->scenes->List()) *resp->add_scenes() = std::move(s);
  return grpc::Status::OK;
}

grpc::Status SceneServiceImpl::GetScene(grpc::ServerContext* ctx, const v1::GetSceneRequest* req, v1::Scene* resp) {
  STREETSIM_AUTH(ctx);
  absl::StatusOr<v1::Scene> s = deps_->scenes->Get(req->name());
  if (!s.ok()) return ToGrpcStatus(s.status());
  *resp = std::move(*s);
  return grpc::Status::OK;
}

grpc::Status SceneServiceImpl::LoadScene(grpc::ServerContext* ctx, const v1::LoadSceneRequest* req,
                                         v1::LoadSceneResponse* resp) {
  STREETSIM_AUTH(ctx);
  absl::StatusOr<v1::Scene> s = deps_->scenes->Load(req->name(), req->wait(), ContextCancelCheck(ctx));
  if (!s.ok()) return ToGrpcStatus(s.status());
  *resp->mutable_scene() = std::move(*s);
  return grpc::Status::OK;
}

grpc::Status SceneServiceImpl::UnloadScene(grpc::ServerContext* ctx, const v1::UnloadSceneRequest* req,
                                           v1::UnloadSceneResponse*) {
  STREETSIM_AUTH(ctx);
  return ToGrpcStatus(deps_->scenes->Unload(req->name()));
}

}  // namespace streetsim::server
