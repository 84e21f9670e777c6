#include "client/cpp/streetsim_client.h"

#include <chrono>
#include <cstring>
#include <fstream>
#include <sstream>

#include <grpcpp/create_channel.h>
#include <grpcpp/security/credentials.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"

namespace streetsim::client {

absl::Status FromGrpcStatus(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  // gRPC's canonical codes and absl's share their numbering.
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()), status.error_message());
}

absl::StatusOr<std::unique_ptr<Client>> Client::Connect(const ClientOptions& options) {
  auto c = std::unique_ptr<Client>(new Client());
  c->options_ = options;
  std::shared_ptr<grpc::ChannelCredentials> creds = grpc::InsecureChannelCredentials();
  if (!options.tls_root_cert_file.empty()) {
    std::ifstream in(options.tls_root_cert_file);
    if (!in) return absl::InvalidArgumentError(absl::StrCat(options.tls_root_cert_file, ": cannot open"));
    std::stringstream ss;
    ss << in.rdbuf();
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = ss.str();
    creds = grpc::SslCredentials(ssl);
  }
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(static_cast<int>(std::min<int64_t>(options.max_message_bytes, INT32_MAX)));
  args.SetMaxSendMessageSize(static_cast<int>(std::min<int64_t>(options.max_message_bytes, INT32_MAX)));
  args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS, 30000);
  c->channel_ = grpc::CreateCustomChannel(options.target, creds, args);
  c->health_ = grpc::health::v1::Health::NewStub(c->channel_);
  c->info_ = v1::ServerInfoService::NewStub(c->channel_);
  c->scenes_ = v1::SceneService::NewStub(c->channel_);
  c->render_ = v1::RenderService::NewStub(c->channel_);
  c->sessions_ = v1::SessionService::NewStub(c->channel_);
  c->training_ = v1::TrainingService::NewStub(c->channel_);
  return c;
}

void Client::Prepare(grpc::ClientContext* ctx, double timeout_s) const {
  const double t = timeout_s < 0 ? options_.timeout_s : timeout_s;
  ctx->set_deadline(std::chrono::system_clock::now() +
                    std::chrono::microseconds(static_cast<int64_t>(t * 1e6)));
  if (!options_.token.empty()) ctx->AddMetadata("authorization", "Bearer " + options_.token);
}

absl::Status Client::WaitForReady(double timeout_s) {
  const auto deadline = std::chrono::system_clock::now() +
                        std::chrono::microseconds(static_cast<int64_t>(timeout_s * 1e6));
  if (!channel_->WaitForConnected(deadline)) {
    return absl::UnavailableError(absl::StrCat("cannot connect to ", options_.target));
  }
  return absl::OkStatus();
}

#define STREETSIM_UNARY(stub, method, request, ResponseT)      \
  grpc::ClientContext ctx;                                     \
  Prepare(&ctx);                                               \
  ResponseT response;                                          \
  grpc::Status st = stub->method(&ctx, request, &response);    \
  if (!st.ok()) return FromGrpcStatus(st);

absl::StatusOr<bool> Client::IsServing(const std::string& service) {
  grpc::health::v1::HealthCheckRequest req;
  req.set_service(service);
  STREETSIM_UNARY(health_, Check, req, grpc::health::v1::HealthCheckResponse);
  return response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
}

absl::StatusOr<v1::ServerInfo> Client::GetServerInfo() {
  STREETSIM_UNARY(info_, GetServerInfo, v1::GetServerInfoRequest(), v1::ServerInfo);
  return response;
}

absl::StatusOr<std::vector<v1::Scene>> Client::ListScenes() {
  STREETSIM_UNARY(scenes_, ListScenes, v1::ListScenesRequest(), v1::ListScenesResponse);
  return std::vector<v1::Scene>(response.scenes().begin(), response.scenes().end());
}

absl::StatusOr<v1::Scene> Client::GetScene(const std::string& name) {
  v1::GetSceneRequest req;
  req.set_name(name);
  STREETSIM_UNARY(scenes_, GetScene, req, v1::Scene);
  return response;
}

absl::StatusOr<v1::Scene> Client::LoadScene(const std::string& name, bool wait) {
  v1::LoadSceneRequest req;
  req.set_name(name);
  req.set_wait(wait);
  STREETSIM_UNARY(scenes_, LoadScene, req, v1::LoadSceneResponse);
  return response.scene();
}

absl::Status Client::UnloadScene(const std::string& name) {
  v1::UnloadSceneRequest req;
  req.set_name(name);
  STREETSIM_UNARY(scenes_, UnloadScene, req, v1::UnloadSceneResponse);
  return absl::OkStatus();
}

absl::StatusOr<v1::RenderResponse> Client::Render(const v1::RenderRequest& request) {
  STREETSIM_UNARY(render_, Render, request, v1::RenderResponse);
  return response;
}

absl::Status Client::RenderTrajectory(const v1::RenderTrajectoryRequest& request,
                                      const std::function<absl::Status(const v1::TrajectoryFrame&)>& on_frame) {
  grpc::ClientContext ctx;
  Prepare(&ctx);
  std::unique_ptr<grpc::ClientReader<v1::TrajectoryFrame>> reader = render_->RenderTrajectory(&ctx, request);
  v1::TrajectoryFrame frame;
  while (reader->Read(&frame)) {
    if (absl::Status s = on_frame(frame); !s.ok()) {
      ctx.TryCancel();
      reader->Finish();
      return s;
    }
  }
  return FromGrpcStatus(reader->Finish());
}

absl::StatusOr<v1::Session> Client::CreateSession(const v1::CreateSessionRequest& request) {
  STREETSIM_UNARY(sessions_, CreateSession, request, v1::Session);
  return response;
}

absl::StatusOr<v1::Session> Client::GetSession(const std::string& id) {
  v1::GetSessionRequest req;
  req.set_session_id(id);
  STREETSIM_UNARY(sessions_, GetSession, req, v1::Session);
  return response;
}

absl::StatusOr<v1::Session> Client::ForkSession(const std::string& id) {
  v1::ForkSessionRequest req;
  req.set_session_id(id);
  STREETSIM_UNARY(sessions_, ForkSession, req, v1::Session);
  return response;
}

absl::Status Client::CloseSession(const std::string& id) {
  v1::CloseSessionRequest req;
  req.set_session_id(id);
  STREETSIM_UNARY(sessions_, CloseSession, req, v1::CloseSessionResponse);
  return absl::OkStatus();
}

absl::StatusOr<v1::StepResponse> Client::Step(const v1::StepRequest& request, double timeout_s) {
  grpc::ClientContext ctx;
  Prepare(&ctx, timeout_s);
  v1::StepResponse response;
  grpc::Status st = sessions_->Step(&ctx, request, &response);
  if (!st.ok()) return FromGrpcStatus(st);
  return response;
}

absl::StatusOr<v1::Job> Client::CreateTrainingJob(const v1::CreateTrainingJobRequest& request) {
  STREETSIM_UNARY(training_, CreateTrainingJob, request, v1::Job);
  return response;
}

absl::StatusOr<v1::Job> Client::GetJob(const std::string& id) {
  v1::GetJobRequest req;
  req.set_job_id(id);
  STREETSIM_UNARY(training_, GetJob, req, v1::Job);
  return response;
}

absl::StatusOr<std::vector<v1::Job>> Client::ListJobs() {
  STREETSIM_UNARY(training_, ListJobs, v1::ListJobsRequest(), v1::ListJobsResponse);
  return std::vector<v1::Job>(response.jobs().begin(), response.jobs().end());
}

absl::StatusOr<v1::Job> Client::CancelJob(const std::string& id) {
  v1::CancelJobRequest req;
  req.set_job_id(id);
  STREETSIM_UNARY(training_, CancelJob, req, v1::Job);
  return response;
}

absl::StatusOr<v1::Job> Client::WatchJob(const std::string& id, const std::function<void(const v1::Job&)>& on_update,
                                         double timeout_s) {
  grpc::ClientContext ctx;
  Prepare(&ctx, timeout_s);
  v1::WatchJobRequest req;
  req.set_job_id(id);
  std::unique_ptr<grpc::ClientReader<v1::Job>> reader = training_->WatchJob(&ctx, req);
  v1::Job job, last;
  bool any = false;
  while (reader->Read(&job)) {
    on_update(job);
    last = job;
    any = true;
  }
  if (absl::Status s = FromGrpcStatus(reader->Finish()); !s.ok()) return s;
  if (!any) return absl::InternalError("WatchJob ended without an update");
  return last;
}

namespace {

template <typename T>
absl::Status Unpack(const std::string& bytes, size_t count, const char* what, std::vector<T>* out) {
  if (bytes.size() != count * sizeof(T)) {
    return absl::DataLossError(absl::StrCat("lidar ", what, ": ", bytes.size(), " bytes, expected ", count * sizeof(T)));
  }
  out->resize(count);
  if (count) std::memcpy(out->data(), bytes.data(), bytes.size());
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<DecodedLidar> DecodeLidar(const v1::LidarResult& lidar) {
  DecodedLidar out;
  if (lidar.beams() < 0 || lidar.columns() < 0) return absl::DataLossError("lidar: negative size");
  out.beams = lidar.beams();
  out.columns = lidar.columns();
  const size_t n = size_t(out.beams) * out.columns;
  if (absl::Status s = Unpack(lidar.range(), n, "range", &out.range); !s.ok()) return s;
  if (absl::Status s = Unpack(lidar.intensity(), n, "intensity", &out.intensity); !s.ok()) return s;
  if (absl::Status s = Unpack(lidar.alpha(), n, "alpha", &out.alpha); !s.ok()) return s;
  if (lidar.has_points()) {
    const v1::LidarPointCloud& p = lidar.points();
    const size_t m = p.count();
    std::vector<float> xyz;
    if (absl::Status s = Unpack(p.xyz(), 3 * m, "points.xyz", &xyz); !s.ok()) return s;
    out.points.resize(m);
    for (size_t i = 0; i < m; ++i) out.points[i] = Eigen::Vector3f(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
    if (absl::Status s = Unpack(p.intensity(), m, "points.intensity", &out.point_intensity); !s.ok()) return s;
    if (absl::Status s = Unpack(p.time_us(), m, "points.time_us", &out.point_time_us); !s.ok()) return s;
    if (absl::Status s = Unpack(p.beam(), m, "points.beam", &out.point_beam); !s.ok()) return s;
    if (absl::Status s = Unpack(p.column(), m, "points.column", &out.point_column); !s.ok()) return s;
  }
  return out;
}

absl::StatusOr<DecodedImage> DecodeImage(const v1::Image& image) {
  DecodedImage out;
  out.width = image.width();
  out.height = image.height();
  const size_t n = size_t(out.width) * out.height;
  const std::string& data = image.data();
  if (image.encoding() == v1::IMAGE_ENCODING_RAW || image.encoding() == v1::IMAGE_ENCODING_UNSPECIFIED) {
    if (image.format() == v1::IMAGE_FORMAT_RGB8) {
      if (data.size() != n * 3) return absl::DataLossError("RGB8 image has the wrong size");
      out.channels = 3;
      out.u8.assign(data.begin(), data.end());
    } else if (image.format() == v1::IMAGE_FORMAT_F32) {
      if (data.size() != n * 4) return absl::DataLossError("F32 image has the wrong size");
      out.channels = 1;
      out.f32.resize(n);
      std::memcpy(out.f32.data(), data.data(), n * 4);
    } else {
      return absl::UnimplementedError("unknown raw image format");
    }
    return out;
  }
  cv::Mat buf(1, static_cast<int>(data.size()), CV_8UC1, const_cast<char*>(data.data()));
  cv::Mat m = cv::imdecode(buf, cv::IMREAD_UNCHANGED);
  if (m.empty() || m.cols != out.width || m.rows != out.height) return absl::DataLossError("cannot decode image");
  if (image.format() == v1::IMAGE_FORMAT_RGB8) {
    cv::Mat rgb;
    cv::cvtColor(m, rgb, cv::COLOR_BGR2RGB);
    out.channels = 3;
    out.u8.assign(rgb.data, rgb.data + n * 3);
  } else if (image.format() == v1::IMAGE_FORMAT_U16) {
    out.channels = 1;
    out.f32.resize(n);
    for (size_t i = 0; i < n; ++i) out.f32[i] = float(m.at<uint16_t>(static_cast<int>(i)) * image.scale());
  } else if (image.format() == v1::IMAGE_FORMAT_U8) {
    out.channels = 1;
    out.u8.assign(m.data, m.data + n);
    out.f32.resize(n);
    for (size_t i = 0; i < n; ++i) out.f32[i] = out.u8[i] / 255.0f;
  } else {
    return absl::UnimplementedError("unknown image format");
  }
  return out;
}

namespace {
v1::ActorEdit ActorEditOf(v1::ActorEditKind kind, int actor_id, const ActorTrajectory& trajectory) {
  v1::ActorEdit e;
  e.set_kind(kind);
  e.set_actor_id(actor_id);
  for (const auto& [time_us, T] : trajectory) {
    v1::ActorPose* p = e.add_trajectory();
    p->set_time_us(time_us);
    *p->mutable_t_world_from_actor() = ToPose(T);
  }
  return e;
}
}  // namespace

v1::ActorEdit RemoveActor(int actor_id) { return ActorEditOf(v1::ACTOR_EDIT_REMOVE, actor_id, {}); }
v1::ActorEdit MoveActor(int actor_id, const ActorTrajectory& trajectory) {
  return ActorEditOf(v1::ACTOR_EDIT_MOVE, actor_id, trajectory);
}
v1::ActorEdit InsertActor(int actor_id, const ActorTrajectory& trajectory) {
  return ActorEditOf(v1::ACTOR_EDIT_INSERT, actor_id, trajectory);
}

v1::Pose ToPose(const Eigen::Isometry3d& T) {
  v1::Pose p;
  Eigen::Quaterniond q(T.rotation());
  q.normalize();
  p.mutable_translation_m()->set_x(T.translation().x());
  p.mutable_translation_m()->set_y(T.translation().y());
  p.mutable_translation_m()->set_z(T.translation().z());
  p.mutable_rotation()->set_w(q.w());
  p.mutable_rotation()->set_x(q.x());
  p.mutable_rotation()->set_y(q.y());
  p.mutable_rotation()->set_z(q.z());
  return p;
}

Eigen::Isometry3d FromPose(const v1::Pose& pose) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Quaterniond(pose.rotation().w(), pose.rotation().x(), pose.rotation().y(),
                                  pose.rotation().z()).normalized().toRotationMatrix();
  T.translation() = Eigen::Vector3d(pose.translation_m().x(), pose.translation_m().y(), pose.translation_m().z());
  return T;
}

}  // namespace streetsim::client
