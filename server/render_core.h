// The one gate to the render engine: admits a request by its cost before anything else
// (admission.h), queues renders fairly across clients (fair_gate.h), serialises engine calls,
// stops on the client's deadline or cancel between stages and tiles, and encodes outputs.
#pragma once

#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "server/lidar_request.h"
#include "server/fair_gate.h"
#include "server/lidar_sweeper.h"
#include "server/limits.h"
#include "server/proto_convert.h"
#include "server/scene_field.h"
#include "streetsim/v1/common.pb.h"

namespace grpc {
class ServerContext;
class ServerContextBase;
}

namespace streetsim::server {

// Returns OK to go on, DEADLINE_EXCEEDED or CANCELLED to stop.
using CancelCheck = std::function<absl::Status()>;
CancelCheck ContextCancelCheck(const grpc::ServerContextBase* ctx);

struct CameraView {
  std::string sensor_id;
  Intrinsics intrinsics;
  Eigen::Isometry3d T_world_from_sensor = Eigen::Isometry3d::Identity();
};

struct RenderResult {
  std::vector<v1::SensorFrame> frames;
  std::optional<v1::LidarResult> lidar;
  v1::Timings timings;
  std::string content_digest;
};

// What a render adds to the cameras: the scene's learned background (used unless the request
// sets one) and a LiDAR sweep.
struct RenderExtras {
  std::optional<Eigen::Vector3f> default_background;
  const LidarJob* lidar = nullptr;
  // Who asks, for fair queueing: a session's id for its steps, the caller's identity otherwise.
  std::string client;
};

class RenderCore {
 public:
  RenderCore(std::unique_ptr<Engine> engine, const ServerLimits& limits, int debug_delay_ms,
             LidarDevice lidar_device = LidarDevice::kFollowEngine);

  // Engine::Upload under the engine lock.
  absl::StatusOr<std::unique_ptr<DeviceScene>> Upload(const GaussianStore& store);

  // Renders every view of `field` at time_us (and the LiDAR sweep when extras.lidar is set); all
  // or nothing. `outputs` already validated. Admission (admission.h) is checked first; callers
  // that do expensive work before (loading a scene) check it themselves too.
  absl::StatusOr<RenderResult> Render(const SceneField& field, int64_t time_us,
                                      const std::vector<CameraView>& views,
                                      const v1::OutputSpec& outputs, const CancelCheck& cancel,
                                      const RenderExtras& extras = {});

  int in_flight() const { return gate_.in_flight(); }
  std::string backend_name() const;
  std::string device_name() const;
  // Where sweeps run ("" until the first LiDAR request creates the renderer).
  std::string lidar_device_name();

 private:
  // Sweeps `job` of `host` (uploading it first unless it is the one uploaded last).
  absl::Status RenderLidar(const std::shared_ptr<const HostScene>& host, const LidarJob& job,
                           LidarRenderOutput* out);

  std::unique_ptr<Engine> engine_;
  // Under engine_mu_ (one renderer at a time: both use every core, or the same GPU). Created on
  // first use (lidar_sweeper.h: on the engine's GPU when it has one, else the cpu).
  std::unique_ptr<LidarSweeper> lidar_;
  LidarDevice lidar_device_;
  uint64_t lidar_generation_ = 0;  // HostScene::generation of what the LiDAR renderer holds
  ServerLimits limits_;
  int debug_delay_ms_;
  FairGate gate_;         // whose render is next
  std::mutex engine_mu_;  // the engine itself (renders and uploads)
};

}  // namespace streetsim::server
