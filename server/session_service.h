// streetsim.v1.SessionService over SessionManager.
#pragma once

#include "server/service_deps.h"
#include "server/session_manager.h"
#include "streetsim/v1/session.grpc.pb.h"

namespace streetsim::server {

class SessionServiceImpl final : public v1::SessionService::Service {
 public:
  explicit SessionServiceImpl(ServiceDeps* deps) : deps_(deps) {}
  grpc::Status CreateSession(grpc::ServerContext* ctx, const v1::CreateSessionRequest* req, v1::Session* resp) override;
  grpc::Status GetSession(grpc::ServerContext* ctx, const v1::GetSessionRequest* req, v1::Session* resp) override;
  grpc::Status ListSessions(grpc::ServerContext* ctx, const v1::ListSessionsRequest* req,
                            v1::ListSessionsResponse* resp) override;
  grpc::Status CloseSession(grpc::ServerContext* ctx, const v1::CloseSessionRequest* req,
                            v1::CloseSessionResponse* resp) override;
  grpc::Status Step(grpc::ServerContext* ctx, const v1::StepRequest* req, v1::StepResponse* resp) override;
  grpc::Status Drive(grpc::ServerContext* ctx,
                     grpc::ServerReaderWriter<v1::StepResponse, v1::StepRequest>* stream) override;
  grpc::Status ForkSession(grpc::ServerContext* ctx, const v1::ForkSessionRequest* req, v1::Session* resp) override;

 private:
  ServiceDeps* deps_;
};

}  // namespace streetsim::server
