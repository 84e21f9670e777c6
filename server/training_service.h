// streetsim.v1.TrainingService over JobRunner / JobStore.
#pragma once

#include "server/job_runner.h"
#include "server/service_deps.h"
#include "streetsim/v1/training.grpc.pb.h"

namespace streetsim::server {

class TrainingServiceImpl final : public v1::TrainingService::Service {
 public:
  explicit TrainingServiceImpl(ServiceDeps* deps) : deps_(deps) {}
  grpc::Status CreateTrainingJob(grpc::ServerContext* ctx, const v1::CreateTrainingJobRequest* req,
                                 v1::Job* resp) override;
  grpc::Status GetJob(grpc::ServerContext* ctx, const v1::GetJobRequest* req, v1::Job* resp) override;
  grpc::Status ListJobs(grpc::ServerContext* ctx, const v1::ListJobsRequest* req, v1::ListJobsResponse* resp) override;
  grpc::Status CancelJob(grpc::ServerContext* ctx, const v1::CancelJobRequest* req, v1::Job* resp) override;
  grpc::Status WatchJob(grpc::ServerContext* ctx, const v1::WatchJobRequest* req,
                        grpc::ServerWriter<v1::Job>* writer) override;

 private:
  ServiceDeps* deps_;
};

}  // namespace streetsim::server
