#include "server/training_service.h"

#include "absl/strings/str_cat.h"
#include "server/echo.h"
#include "server/status_mapping.h"

namespace streetsim::server {

#define STREETSIM_AUTH(ctx)                                                \
  if (absl::Status _s = deps_->auth.Check(*(ctx)); !_s.ok()) return ToGrpcStatus(_s)

static grpc::Status UnknownJob(const std::string& id) {
  return grpc::Status(grpc::StatusCode::NOT_FOUND, absl::StrCat("unknown job ", Echo(id)));
}

grpc::Status TrainingServiceImpl::CreateTrainingJob(grpc::ServerContext* ctx, const v1::CreateTrainingJobRequest* req,
                                                    v1::Job* resp) {
  STREETSIM_AUTH(ctx);
  absl::StatusOr<v1::Job> job = deps_->jobs->Create(*req);
  if (!job.ok()) return ToGrpcStatus(job.status());
  *resp = *job;
  return grpc::Status::OK;
}

grpc::Status TrainingServiceImpl::GetJob(grpc::ServerContext* ctx, const v1::GetJobRequest* req, v1::Job* resp) {
  STREETSIM_AUTH(ctx);
  std::optional<v1::Job> job = deps_->jobs->store()->Get(req->job_id());
  if (!job) return UnknownJob(req->job_id());
  *resp = *job;
  return grpc::Status::OK;
}

grpc::Status TrainingServiceImpl::ListJobs(grpc::ServerContext* ctx, const v1::ListJobsRequest*,
                                           v1::ListJobsResponse* resp) {
  STREETSIM_AUTH(ctx);
  for (v1::Job& job : deps_->jobs->store()->List()) *resp->add_jobs() = std::move(job);
  return grpc::Status::OK;
}

grpc::Status TrainingServiceImpl::CancelJob(grpc::ServerContext* ctx, const v1::CancelJobRequest* req, v1::Job* resp) {
  STREETSIM_AUTH(ctx);
  absl::StatusOr<v1::Job> job = deps_->jobs->Cancel(req->job_id());
  if (!job.ok()) return ToGrpcStatus(job.status());
  *resp = *job;
  return grpc::Status::OK;
}

grpc::Status TrainingServiceImpl::WatchJob(grpc::ServerContext* ctx, const v1::WatchJobRequest* req,
                                           grpc::ServerWriter<v1::Job>* writer) {
  STREETSIM_AUTH(ctx);
  JobStore* store = deps_->jobs->store();
  std::string sent;  // the last record sent, serialised
  auto last_send = std::chrono::steady_clock::now();
  uint64_t version = store->version();
  while (true) {
    std::optional<v1::Job> job = store->Get(req->job_id());
    if (!job) return UnknownJob(req->job_id());
    const auto now = std::chrono::steady_clock::now();
    std::string bytes = job->SerializeAsString();
    if (bytes != sent || now - last_send > std::chrono::seconds(2)) {
      if (!writer->Write(*job)) return grpc::Status(grpc::StatusCode::CANCELLED, "client went away");
      sent = std::move(bytes);
      last_send = now;
    }
    if (IsFinal(job->state())) return grpc::Status::OK;
    if (ctx->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "cancelled");
    if (deps_->draining) return grpc::Status(grpc::StatusCode::UNAVAILABLE, "server is shutting down");
    version = store->WaitForChange(version, std::chrono::milliseconds(200));
  }
}

}  // namespace streetsim::server
