#include "server/render_core.h"

#include <chrono>
#include <thread>

#include <grpcpp/server_context.h>

#include "absl/strings/str_cat.h"
#include "server/admission.h"
#include "server/digest.h"
#include "server/image_encoding.h"

namespace streetsim::server {
namespace {

double MsSince(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

}  // namespace

CancelCheck ContextCancelCheck(const grpc::ServerContextBase* ctx) {
  return [ctx]() -> absl::Status {
    if (ctx->deadline() < std::chrono::system_clock::now()) {
      return absl::DeadlineExceededError("deadline exceeded");
    }
    if (ctx->IsCancelled()) return absl::CancelledError("cancelled by the client");
    return absl::OkStatus();
  };
}

RenderCore::RenderCore(std::unique_ptr<Engine> engine, const ServerLimits& limits, int debug_delay_ms,
                       LidarDevice lidar_device)
    : engine_(std::move(engine)),
      lidar_device_(lidar_device),
      limits_(limits),
      debug_delay_ms_(debug_delay_ms),
      gate_(limits.max_queued_renders, limits.max_queued_renders_per_client) {}

std::string RenderCore::backend_name() const { return std::string(BackendName(engine_->backend())); }
std::string RenderCore::device_name() const { return engine_->device_name(); }

std::string RenderCore::lidar_device_name() {
  std::lock_guard<std::mutex> lock(engine_mu_);
  return lidar_ ? lidar_->device_name() : std::string();
}

absl::StatusOr<std::unique_ptr<DeviceScene>> RenderCore::Upload(const GaussianStore& store) {
  std::lock_guard<std::mutex> lock(engine_mu_);
  return engine_->Upload(store);
}

absl::Status RenderCore::RenderLidar(const std::shared_ptr<const HostScene>& host, const LidarJob& job,
                                     LidarRenderOutput* out) {
  if (!lidar_) {
    absl::StatusOr<std::unique_ptr<LidarSweeper>> created = CreateLidarSweeper(engine_->backend(), lidar_device_);
    if (!created.ok()) {
      return absl::UnavailableError(absl::StrCat("LiDAR renderer unavailable: ", created.status().message()));
    }
    lidar_ = *std::move(created);
  }
  if (lidar_generation_ != host->generation) {
    const bool follows = host->change && host->previous_generation != 0 && lidar_generation_ == host->previous_generation;
    lidar_generation_ = 0;
    if (absl::Status s = follows ? lidar_->UpdateRows(host->gaussians(), *host->change) : lidar_->Upload(host->gaussians());
        !s.ok()) {
      return absl::InternalError(absl::StrCat("LiDAR upload failed: ", s.message()));
    }
    lidar_generation_ = host->generation;
  }
  LidarRenderOptions options = job.options;
  options.reflectance = host->reflectance ? &*host->reflectance : nullptr;
  if (absl::Status s = lidar_->Render(job.model, job.sweep, options, out); !s.ok()) {
    // The request was validated; what is left is the pose (e.g. a non-rigid ego pose product).
    return absl::InvalidArgumentError(absl::StrCat("lidar: ", s.message()));
  }
  return absl::OkStatus();
}

absl::StatusOr<RenderResult> RenderCore::Render(const SceneField& field, int64_t time_us,
                                                const std::vector<CameraView>& views,
                                                const v1::OutputSpec& outputs,
                                                const CancelCheck& cancel, const RenderExtras& extras) {
  const auto t0 = std::chrono::steady_clock::now();
  if (absl::Status s = AdmitRender(EstimateRenderCost(views, outputs, extras.lidar), limits_); !s.ok()) return s;
  FairGate::Pass pass;
  if (absl::Status s = gate_.Enter(extras.client, cancel, &pass); !s.ok()) return s;
  std::unique_lock<std::mutex> lock(engine_mu_);
  RenderResult result;
  result.timings.set_queue_ms(MsSince(t0));
  if (absl::Status s = cancel(); !s.ok()) return s;

  if (debug_delay_ms_ > 0) {  // test hook: a slow renderer, cancellable like a real one
    const auto until = std::chrono::steady_clock::now() + std::chrono::milliseconds(debug_delay_ms_);
    while (std::chrono::steady_clock::now() < until) {
      if (absl::Status s = cancel(); !s.ok()) return s;
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
  }

  // A dynamic scene evaluates its field here (once per new timestamp, counted in render_ms),
  // under the engine lock.
  const auto t_render = std::chrono::steady_clock::now();
  absl::StatusOr<const DeviceScene*> scene = field.At(time_us, *engine_);
  if (!scene.ok()) return scene.status();
  RenderOptions options;
  options.should_stop = [&cancel] { return !cancel().ok(); };
  options.want_depth = outputs.depth();
  options.want_alpha = outputs.alpha();
  if (outputs.has_background_rgb()) {
    options.background = Eigen::Vector3f(outputs.background_rgb().x(), outputs.background_rgb().y(),
                                         outputs.background_rgb().z());
  } else if (std::optional<Eigen::Vector3f> bg = field.BackgroundAt(time_us)) {
    options.background = *bg;
  } else if (extras.default_background) {
    options.background = *extras.default_background;
  }
  std::vector<RenderOutput> rendered(views.size());
  for (size_t i = 0; i < views.size(); ++i) {
    if (absl::Status s = cancel(); !s.ok()) return s;
    PinholeCamera cam;
    cam.width = views[i].intrinsics.width;
    cam.height = views[i].intrinsics.height;
    cam.fx = views[i].intrinsics.fx;
    cam.fy = views[i].intrinsics.fy;
    cam.cx = views[i].intrinsics.cx;
    cam.cy = views[i].intrinsics.cy;
    cam.T_world_from_cam = views[i].T_world_from_sensor;
    if (absl::Status s = cam.Validate(); !s.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("sensor ", views[i].sensor_id, ": ", s.message()));
    }
    if (absl::Status s = engine_->Render(**scene, cam, options, &rendered[i]); !s.ok()) {
      if (absl::Status c = cancel(); !c.ok()) return c;  // stopped part-way for the client
      return absl::InternalError(absl::StrCat("render failed: ", s.message()));
    }
  }
  LidarRenderOutput lidar_out;
  if (extras.lidar) {
    if (absl::Status s = cancel(); !s.ok()) return s;
    absl::StatusOr<std::shared_ptr<const HostScene>> host = field.GeometryAt(time_us);
    if (!host.ok()) return host.status();
    if (absl::Status s = RenderLidar(*host, *extras.lidar, &lidar_out); !s.ok()) return s;
  }
  result.timings.set_render_ms(MsSince(t_render));
  lock.unlock();
  pass = FairGate::Pass();  // the next client renders while this one encodes

  if (absl::Status s = cancel(); !s.ok()) return s;
  const auto t_encode = std::chrono::steady_clock::now();
  // The response's digest is taken over its items' digests, so no payload is hashed twice.
  ContentDigest digest;
  for (size_t i = 0; i < views.size(); ++i) {
    const RenderOutput& r = rendered[i];
    v1::SensorFrame frame;
    frame.set_sensor_id(views[i].sensor_id);
    IntrinsicsToProto(views[i].intrinsics, frame.mutable_intrinsics());
    PoseToProto(views[i].T_world_from_sensor, frame.mutable_t_world_from_sensor());
    frame.set_num_visible_gaussians(r.stats.num_visible);
    if (outputs.rgb()) {
      if (absl::Status s = EncodeRgb(r.width, r.height, r.rgb, outputs.rgb_encoding(),
                                     outputs.jpeg_quality(), frame.mutable_rgb());
          !s.ok()) return s;
      digest.Update(frame.rgb().digest());
    }
    if (outputs.depth()) {
      if (absl::Status s = EncodeDepth(r.width, r.height, r.depth, outputs.depth_encoding(),
                                       frame.mutable_depth());
          !s.ok()) return s;
      digest.Update(frame.depth().digest());
    }
    if (outputs.alpha()) {
      if (absl::Status s = EncodeAlpha(r.width, r.height, r.alpha, outputs.alpha_encoding(),
                                       frame.mutable_alpha());
          !s.ok()) return s;
      digest.Update(frame.alpha().digest());
    }
    result.frames.push_back(std::move(frame));
  }
  if (extras.lidar) {
    const auto t_lidar = std::chrono::steady_clock::now();
    v1::LidarResult lidar;
    LidarResultToProto(*extras.lidar, lidar_out, &lidar);
    lidar.mutable_timings()->set_encode_ms(MsSince(t_lidar));
    digest.Update(lidar.digest());
    result.lidar = std::move(lidar);
  }
  result.timings.set_encode_ms(MsSince(t_encode));
  result.timings.set_total_ms(MsSince(t0));
  result.content_digest = digest.Hex();
  return result;
}

}  // namespace streetsim::server
