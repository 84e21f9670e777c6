// The streetsim gRPC server: builder, listening address (127.0.0.1 by default), TLS, bearer
// token, health + reflection, the streetsim.v1 services, and graceful shutdown.
#pragma once

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "scene/train/dynamic_stage.h"
#include "server/limits.h"

namespace grpc {
class Server;
class Service;
}

namespace streetsim::server {

struct ServerOptions {
  std::string listen = "127.0.0.1:50051";  // port 0: pick a free one (see Server::port)
  std::string data_root = "./data";
  std::string state_dir = "./state";
  Backend backend = Backend::kAuto;
  // Where dynamic scenes evaluate their field (docs/server.md "Field device"): kAuto = Vulkan when
  // the engine is vulkan on a GPU (never lavapipe: slower than the cpu there), else the cpu.
  train::FieldDevice field_device = train::FieldDevice::kAuto;
  // Dynamic scenes' static skip (docs/field.md "Serving": thresholds below which a Gaussian's
  // deformation over the log is baked in; `streetsim serve --static-motion-m / --static-sh`).
  field::StaticSkipOptions static_skip;
  // true (`--field-serving exact`): dynamic scenes evaluate the field's network per timestamp
  // instead of its serving form (docs/field.md "Serving form").
  bool exact_field = false;
  field::ServingFormOptions serving_form;  // its fit (no flag: tests and benchmarks)
  std::string tls_cert_file;   // both or neither
  std::string tls_key_file;
  std::string auth_token_file;  // bearer token; empty: no auth
  ServerLimits limits;
  // This server's name among replicas sharing state_dir (server/replica.h); "" when alone.
  std::string replica;
  // Training stages' argv prefixes: `streetsim serve` passes its own binary; tests override; empty:
  // the `streetsim init` / `streetsim train` next to this binary (train: if its help lists it).
  std::vector<std::string> init_command;
  std::vector<std::string> train_command;
  int debug_render_delay_ms = 0;          // tests only: a slow renderer
};

struct ServiceDeps;
class RenderCore;
class SceneRegistry;
class SessionManager;
class JobStore;
class JobRunner;

class Server {
 public:
  static absl::StatusOr<std::unique_ptr<Server>> Start(const ServerOptions& options);
  ~Server();

  int port() const { return port_; }
  std::string address() const;  // host:port actually bound

  // Health NOT_SERVING, new sessions/jobs refused, in-flight calls get `grace` to finish, jobs
  // stop (records stay resumable). Idempotent.
  void Shutdown(std::chrono::milliseconds grace = std::chrono::seconds(10));
  void Wait();

 private:
  Server() = default;
  ServerOptions options_;
  int port_ = 0;
  std::unique_ptr<ServiceDeps> deps_;
  std::unique_ptr<RenderCore> core_;
  std::unique_ptr<SceneRegistry> scenes_;
  std::unique_ptr<SessionManager> sessions_;
  std::unique_ptr<JobStore> job_store_;
  std::unique_ptr<JobRunner> jobs_;
  std::vector<std::unique_ptr<grpc::Service>> services_;
  std::unique_ptr<grpc::Server> server_;
  bool shut_down_ = false;
};

}  // namespace streetsim::server
