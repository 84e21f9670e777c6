#include "server/server.h"

#include <filesystem>
#include <fstream>
#include <sstream>

#include <grpcpp/ext/proto_server_reflection_plugin.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/server.h>
#include <grpcpp/server_builder.h>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "server/replica.h"
#include "server/info_and_scene_services.h"
#include "server/job_runner.h"
#include "server/job_store.h"
#include "server/render_service.h"
#include "server/session_service.h"
#include "server/training_service.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {

const char* const kServiceNames[] = {
    "streetsim.v1.ServerInfoService", "streetsim.v1.SceneService", "streetsim.v1.RenderService",
    "streetsim.v1.SessionService", "streetsim.v1.TrainingService"};

absl::StatusOr<std::string> ReadFile(const std::string& path, const char* flag) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::InvalidArgumentError(absl::StrCat(flag, " ", path, ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void SetHealth(grpc::Server* server, bool serving) {
  grpc::HealthCheckServiceInterface* health = server->GetHealthCheckService();
  if (!health) return;
  health->SetServingStatus(serving);
  for (const char* name : kServiceNames) health->SetServingStatus(name, serving);
}

}  // namespace

absl::StatusOr<std::unique_ptr<Server>> Server::Start(const ServerOptions& options) {
  std::unique_ptr<Server> s(new Server());
  s->options_ = options;
  std::error_code ec;
  if (!fs::is_directory(options.data_root, ec)) {
    return absl::InvalidArgumentError(absl::StrCat("--data-root ", options.data_root, ": not a directory"));
  }
  const std::string data_root = fs::canonical(options.data_root, ec).string();
  fs::create_directories(options.state_dir, ec);
  if (ec) return absl::InvalidArgumentError(absl::StrCat("--state-dir ", options.state_dir, ": ", ec.message()));
  const std::string state_dir = fs::canonical(options.state_dir, ec).string();
  if (options.tls_cert_file.empty() != options.tls_key_file.empty()) {
    return absl::InvalidArgumentError("--tls-cert and --tls-key go together");
  }

  s->deps_ = std::make_unique<ServiceDeps>();
  ServiceDeps& deps = *s->deps_;
  deps.limits = options.limits;
  if (!options.replica.empty()) {
    if (absl::Status st = ValidateReplicaName(options.replica); !st.ok()) return st;
  }
  deps.replica = options.replica;
  if (!options.auth_token_file.empty()) {
    absl::StatusOr<Authenticator> auth = Authenticator::FromFile(options.auth_token_file);
    if (!auth.ok()) return auth.status();
    deps.auth = *auth;
  }
  std::shared_ptr<grpc::ServerCredentials> creds = grpc::InsecureServerCredentials();
  if (!options.tls_cert_file.empty()) {
    absl::StatusOr<std::string> cert = ReadFile(options.tls_cert_file, "--tls-cert");
    if (!cert.ok()) return cert.status();
    absl::StatusOr<std::string> key = ReadFile(options.tls_key_file, "--tls-key");
    if (!key.ok()) return key.status();
    grpc::SslServerCredentialsOptions ssl;
    ssl.pem_key_cert_pairs.push_back({*key, *cert});
    creds = grpc::SslServerCredentials(ssl);
    deps.tls = true;
  }

  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(options.backend);
  if (!engine.ok()) return engine.status();
  SceneLoadOptions load;
  load.field_device = train::ResolveFieldDevice(options.field_device, (*engine)->backend());
  load.static_skip = options.static_skip;
  load.exact_field = options.exact_field;
  load.serving_form = options.serving_form;
  s->core_ = std::make_unique<RenderCore>(std::move(*engine), deps.limits, options.debug_render_delay_ms);
  deps.core = s->core_.get();
  s->job_store_ = std::make_unique<JobStore>(state_dir, options.replica);
  if (absl::Status st = s->job_store_->Init(); !st.ok()) return st;
  s->scenes_ = std::make_unique<SceneRegistry>(data_root, s->job_store_->scenes_dir(), s->core_.get(), load);
  deps.scenes = s->scenes_.get();
  s->sessions_ = std::make_unique<SessionManager>(&deps);
  deps.sessions = s->sessions_.get();
  s->jobs_ = std::make_unique<JobRunner>(s->job_store_.get(), &deps,
                                         JobRunnerOptions{data_root, options.init_command, options.train_command});
  deps.jobs = s->jobs_.get();

  s->services_.push_back(std::make_unique<ServerInfoServiceImpl>(&deps));
  s->services_.push_back(std::make_unique<SceneServiceImpl>(&deps));
  s->services_.push_back(std::make_unique<RenderServiceImpl>(&deps));
  s->services_.push_back(std::make_unique<SessionServiceImpl>(&deps));
  s->services_.push_back(std::make_unique<TrainingServiceImpl>(&deps));

  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(options.listen, creds, &s->port_);
  builder.SetMaxReceiveMessageSize(static_cast<int>(std::min<int64_t>(deps.limits.max_message_bytes, INT32_MAX)));
  builder.SetMaxSendMessageSize(static_cast<int>(std::min<int64_t>(deps.limits.max_message_bytes, INT32_MAX)));
  // Long idle sessions: let clients keep connections alive with pings every >= 10 s.
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 10000);
  for (auto& service : s->services_) builder.RegisterService(service.get());
  s->server_ = builder.BuildAndStart();
  if (!s->server_ || s->port_ == 0) {
    return absl::UnavailableError(absl::StrCat("cannot listen on ", options.listen));
  }
  s->jobs_->Start();
  SetHealth(s->server_.get(), true);
  LOG(INFO) << "streetsim server on " << s->address() << " (" << s->core_->device_name() << ", field on "
            << (load.field_device == train::FieldDevice::kVulkan ? "vulkan" : "cpu") << ", data root "
            << data_root << ", state " << state_dir << (deps.tls ? ", TLS" : "")
            << (deps.auth.enabled() ? ", bearer token" : "") << ")";
  return s;
}

std::string Server::address() const {
  std::string host = options_.listen.substr(0, options_.listen.rfind(':'));
  return absl::StrCat(host, ":", port_);
}

void Server::Shutdown(std::chrono::milliseconds grace) {
  if (shut_down_) return;
  shut_down_ = true;
  deps_->draining = true;
  SetHealth(server_.get(), false);
  server_->Shutdown(std::chrono::system_clock::now() + grace);
  jobs_->Stop();
  LOG(INFO) << "streetsim server stopped";
}

void Server::Wait() { server_->Wait(); }

Server::~Server() {
  if (server_) Shutdown();
}

}  // namespace streetsim::server
