#include "server/session_service.h"

#include "server/status_mapping.h"

namespace streetsim::server {

#define STREETSIM_AUTH(ctx)                                                \
  if (absl::Status _s = deps_->auth.Check(*(ctx)); !_s.ok()) return ToGrpcStatus(_s)

template <typename T>
static grpc::Status Reply(absl::StatusOr<T> r, T* out) {
  if (!r.ok()) return ToGrpcStatus(r.status());
  *out = std::move(*r);
  return grpc::Status::OK;
}

grpc::Status SessionServiceImpl::CreateSession(grpc::ServerContext* ctx, const v1::CreateSessionRequest* req,
                                               v1::Session* resp) {
  STREETSIM_AUTH(ctx);
  return Reply(deps_->sessions->Create(*req), resp);
}

grpc::Status SessionServiceImpl::GetSession(grpc::ServerContext* ctx, const v1::GetSessionRequest* req,
                                            v1::Session* resp) {
  STREETSIM_AUTH(ctx);
  return Reply(deps_->sessions->Get(req->session_id()), resp);
}

grpc::Status SessionServiceImpl::ListSessions(grpc::ServerContext* ctx, const v1::ListSessionsRequest*,
                                              v1::ListSessionsResponse* resp) {
  STREETSIM_AUTH(ctx);
  for (v1::Session& s : deps_->sessions->List()) *resp->add_sessions() = std::move(s);
  return grpc::Status::OK;
}

grpc::Status SessionServiceImpl::CloseSession(grpc::ServerContext* ctx, const v1::CloseSessionRequest* req,
                                              v1::CloseSessionResponse*) {
  STREETSIM_AUTH(ctx);
  return ToGrpcStatus(deps_->sessions->Close(req->session_id()));
}

grpc::Status SessionServiceImpl::Step(grpc::ServerContext* ctx, const v1::StepRequest* req, v1::StepResponse* resp) {
  STREETSIM_AUTH(ctx);
  absl::StatusOr<std::shared_ptr<const v1::StepResponse>> r = deps_->sessions->Step(*req, ContextCancelCheck(ctx));
  if (!r.ok()) return ToGrpcStatus(r.status());
  *resp = **r;
  return grpc::Status::OK;
}

grpc::Status SessionServiceImpl::Drive(grpc::ServerContext* ctx,
                                       grpc::ServerReaderWriter<v1::StepResponse, v1::StepRequest>* stream) {
  STREETSIM_AUTH(ctx);
  const CancelCheck cancel = ContextCancelCheck(ctx);
  v1::StepRequest req;
  while (stream->Read(&req)) {
    absl::StatusOr<std::shared_ptr<const v1::StepResponse>> r = deps_->sessions->Step(req, cancel);
    if (!r.ok()) return ToGrpcStatus(r.status());
    if (!stream->Write(**r)) return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
  }
  return grpc::Status::OK;
}

grpc::Status SessionServiceImpl::ForkSession(grpc::ServerContext* ctx, const v1::ForkSessionRequest* req,
                                             v1::Session* resp) {
  STREETSIM_AUTH(ctx);
  return Reply(deps_->sessions->Fork(req->session_id()), resp);
}

}  // namespace streetsim::server
