// C++ client library for the streetsim gRPC API (proto/streetsim/v1): a connection with
// deadlines and the bearer token on every call, absl::Status errors, and image decoding.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <grpcpp/channel.h>
#include <grpcpp/client_context.h>

#include "absl/status/statusor.h"
#include "streetsim/health/v1/health.grpc.pb.h"
#include "streetsim/v1/render.grpc.pb.h"
#include "streetsim/v1/scene.grpc.pb.h"
#include "streetsim/v1/server_info.grpc.pb.h"
#include "streetsim/v1/session.grpc.pb.h"
#include "streetsim/v1/training.grpc.pb.h"

namespace streetsim::client {

namespace v1 = ::streetsim::v1;

struct ClientOptions {
  std::string target = "127.0.0.1:50051";
  std::string token;               // bearer token ("" = none)
  std::string tls_root_cert_file;  // PEM; set to use TLS
  double timeout_s = 60;           // deadline of every unary call
  int64_t max_message_bytes = 64 << 20;
};

// The canonical gRPC code carried over into absl.
absl::Status FromGrpcStatus(const grpc::Status& status);

class Client {
 public:
  static absl::StatusOr<std::unique_ptr<Client>> Connect(const ClientOptions& options);

  // Waits until the channel is connected (or the timeout passes).
  absl::Status WaitForReady(double timeout_s);
  // grpc.health.v1 Check: SERVING -> true.
  absl::StatusOr<bool> IsServing(const std::string& service = "");

  absl::StatusOr<v1::ServerInfo> GetServerInfo();
  absl::StatusOr<std::vector<v1::Scene>> ListScenes();
  absl::StatusOr<v1::Scene> GetScene(const std::string& name);
  absl::StatusOr<v1::Scene> LoadScene(const std::string& name, bool wait);
  absl::Status UnloadScene(const std::string& name);

  absl::StatusOr<v1::RenderResponse> Render(const v1::RenderRequest& request);
  // Calls on_frame for every streamed frame; stops early if it returns an error.
  absl::Status RenderTrajectory(const v1::RenderTrajectoryRequest& request,
                                const std::function<absl::Status(const v1::TrajectoryFrame&)>& on_frame);

  absl::StatusOr<v1::Session> CreateSession(const v1::CreateSessionRequest& request);
  absl::StatusOr<v1::Session> GetSession(const std::string& id);
  absl::StatusOr<v1::Session> ForkSession(const std::string& id);
  absl::Status CloseSession(const std::string& id);
  absl::StatusOr<v1::StepResponse> Step(const v1::StepRequest& request, double timeout_s = -1);

  absl::StatusOr<v1::Job> CreateTrainingJob(const v1::CreateTrainingJobRequest& request);
  absl::StatusOr<v1::Job> GetJob(const std::string& id);
  absl::StatusOr<std::vector<v1::Job>> ListJobs();
  absl::StatusOr<v1::Job> CancelJob(const std::string& id);
  // Streams job updates until the job ends (returns its final record) or on_update fails.
  absl::StatusOr<v1::Job> WatchJob(const std::string& id, const std::function<void(const v1::Job&)>& on_update,
                                   double timeout_s = 24 * 3600);

  // Sets the deadline (timeout_s < 0: the default) and the token on a context.
  void Prepare(grpc::ClientContext* ctx, double timeout_s = -1) const;
  const std::shared_ptr<grpc::Channel>& channel() const { return channel_; }
  v1::SessionService::Stub* session_stub() { return sessions_.get(); }

 private:
  ClientOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<grpc::health::v1::Health::Stub> health_;
  std::unique_ptr<v1::ServerInfoService::Stub> info_;
  std::unique_ptr<v1::SceneService::Stub> scenes_;
  std::unique_ptr<v1::RenderService::Stub> render_;
  std::unique_ptr<v1::SessionService::Stub> sessions_;
  std::unique_ptr<v1::TrainingService::Stub> training_;
};

// A decoded image: u8 (RGB8: 3 channels; alpha PNG: 1) or f32 (depth metres, alpha 0..1).
struct DecodedImage {
  int width = 0, height = 0, channels = 0;
  std::vector<uint8_t> u8;
  std::vector<float> f32;
};
absl::StatusOr<DecodedImage> DecodeImage(const v1::Image& image);

// A decoded LiDAR sweep (v1::LidarResult): images beams x columns row-major, range metres with 0 =
// no return; points (when the request asked for them) in the result's points frame.
struct DecodedLidar {
  int beams = 0, columns = 0;
  std::vector<float> range, intensity, alpha;
  std::vector<Eigen::Vector3f> points;
  std::vector<float> point_intensity;
  std::vector<int64_t> point_time_us;
  std::vector<uint16_t> point_beam, point_column;
};
// DataLoss when an array's size does not match beams x columns or the point count.
absl::StatusOr<DecodedLidar> DecodeLidar(const v1::LidarResult& lidar);

v1::Pose ToPose(const Eigen::Isometry3d& T);
Eigen::Isometry3d FromPose(const v1::Pose& pose);

// Actor edits (docs/actors.md) for RenderRequest / RenderTrajectoryRequest / CreateSessionRequest
// .actor_edits and StepRequest.actor_edits: a timed pose is (time_us, T_world_from_actor).
using ActorTrajectory = std::vector<std::pair<int64_t, Eigen::Isometry3d>>;
v1::ActorEdit RemoveActor(int actor_id);
v1::ActorEdit MoveActor(int actor_id, const ActorTrajectory& trajectory);    // instead of the log's path
v1::ActorEdit InsertActor(int actor_id, const ActorTrajectory& trajectory);  // a copy; the original stays

}  // namespace streetsim::client
