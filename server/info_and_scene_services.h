// streetsim.v1.ServerInfoService and streetsim.v1.SceneService (both thin).
#pragma once

#include "server/service_deps.h"
#include "streetsim/v1/scene.grpc.pb.h"
#include "streetsim/v1/server_info.grpc.pb.h"

namespace streetsim::server {

inline constexpr char kApiVersion[] = "1.0.0";

class ServerInfoServiceImpl final : public v1::ServerInfoService::Service {
 public:
  explicit ServerInfoServiceImpl(ServiceDeps* deps) : deps_(deps) {}
  grpc::Status GetServerInfo(grpc::ServerContext* ctx, const v1::GetServerInfoRequest* req,
                             v1::ServerInfo* resp) override;

 private:
  ServiceDeps* deps_;
};

class SceneServiceImpl final : public v1::SceneService::Service {
 public:
  explicit SceneServiceImpl(ServiceDeps* deps) : deps_(deps) {}
  grpc::Status ListScenes(grpc::ServerContext* ctx, const v1::ListScenesRequest* req,
                          v1::ListScenesResponse* resp) override;
  grpc::Status GetScene(grpc::ServerContext* ctx, const v1::GetSceneRequest* req, v1::Scene* resp) override;
  grpc::Status LoadScene(grpc::ServerContext* ctx, const v1::LoadSceneRequest* req,
                         v1::LoadSceneResponse* resp) override;
  grpc::Status UnloadScene(grpc::ServerContext* ctx, const v1::UnloadSceneRequest* req,
                           v1::UnloadSceneResponse* resp) override;

 private:
  ServiceDeps* deps_;
};

int64_t CurrentRssBytes();

}  // namespace streetsim::server
