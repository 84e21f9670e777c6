// streetsim.v1.RenderService: stateless renders of a scene from poses.
#pragma once

#include "server/render_core.h"
#include "server/scene_manifest.h"
#include "server/service_deps.h"
#include "streetsim/v1/render.grpc.pb.h"

namespace streetsim::server {

// Sensor poses for a rig at an ego pose.
std::vector<CameraView> ViewsAt(const std::vector<RigCamera>& cameras, const Eigen::Isometry3d& T_world_from_ego);

class RenderServiceImpl final : public v1::RenderService::Service {
 public:
  explicit RenderServiceImpl(ServiceDeps* deps) : deps_(deps) {}
  grpc::Status Render(grpc::ServerContext* ctx, const v1::RenderRequest* req,
                      v1::RenderResponse* resp) override;
  grpc::Status RenderTrajectory(grpc::ServerContext* ctx, const v1::RenderTrajectoryRequest* req,
                                grpc::ServerWriter<v1::TrajectoryFrame>* writer) override;

 private:
  ServiceDeps* deps_;
};

}  // namespace streetsim::server
