// TLS (a self-signed certificate made with the openssl CLI at test time), server reflection
// (grpc.reflection.v1alpha ListServices over a generic stub: no reflection stubs ship with
// Debian's gRPC), and the render queue limit (RESOURCE_EXHAUSTED under a flood, no crash).
#include <sys/wait.h>

#include <atomic>
#include <thread>

#include <google/protobuf/unknown_field_set.h>
#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/support/byte_buffer.h>

#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

// Writes DIR/<name>.crt + DIR/<name>.key: a self-signed EC certificate for 127.0.0.1/localhost.
bool MakeSelfSignedCert(const std::string& dir, const std::string& name) {
  const std::string cmd = "/usr/bin/openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 1"
                          " -subj /CN=localhost -addext subjectAltName=IP:127.0.0.1,DNS:localhost -keyout " +
                          dir + "/" + name + ".key -out " + dir + "/" + name + ".crt >/dev/null 2>&1";
  const int status = std::system(cmd.c_str());
  return WIFEXITED(status) && WEXITSTATUS(status) == 0;
}

class TransportTest : public ServerTest {};

TEST_F(TransportTest, TlsClientConnectsInsecureAndWrongCaClientsFail) {
  const std::string certs = MakeTempDir("certs");
  ASSERT_TRUE(MakeSelfSignedCert(certs, "server"));
  ASSERT_TRUE(MakeSelfSignedCert(certs, "other"));
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.tls_cert_file = certs + "/server.crt";
  o.tls_key_file = certs + "/server.key";
  absl::StatusOr<std::unique_ptr<server::Server>> s = server::Server::Start(o);
  ASSERT_TRUE(s.ok()) << s.status();
  server_ = std::move(*s);

  client::ClientOptions co;
  co.target = server_->address();
  co.timeout_s = 20;
  co.tls_root_cert_file = certs + "/server.crt";
  absl::StatusOr<std::unique_ptr<client::Client>> tls = client::Client::Connect(co);
  ASSERT_TRUE(tls.ok()) << tls.status();
  absl::StatusOr<v1::ServerInfo> info = (*tls)->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_TRUE(info->tls());
  absl::StatusOr<std::vector<v1::Scene>> scenes = (*tls)->ListScenes();
  ASSERT_TRUE(scenes.ok()) << scenes.status();
  EXPECT_FALSE(scenes->empty());
  v1::RenderRequest req;
  req.set_scene("timed");
  req.set_time_us(0);
  req.add_sensors()->set_sensor_id("cam_front");
  req.mutable_outputs()->set_rgb(true);
  absl::StatusOr<v1::RenderResponse> r = (*tls)->Render(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->frames(0).rgb().width(), 128);

  // A plaintext client cannot talk to it.
  co.tls_root_cert_file.clear();
  co.timeout_s = 5;
  absl::StatusOr<std::unique_ptr<client::Client>> plain = client::Client::Connect(co);
  ASSERT_TRUE(plain.ok());
  EXPECT_FALSE((*plain)->GetServerInfo().ok());
  EXPECT_FALSE((*plain)->IsServing().ok());
  // Nor a TLS client that trusts another certificate.
  co.tls_root_cert_file = certs + "/other.crt";
  absl::StatusOr<std::unique_ptr<client::Client>> wrong = client::Client::Connect(co);
  ASSERT_TRUE(wrong.ok());
  EXPECT_FALSE((*wrong)->GetServerInfo().ok());
  // A missing key file is refused at start.
  o.tls_key_file = certs + "/missing.key";
  EXPECT_EQ(server::Server::Start(o).status().code(), absl::StatusCode::kInvalidArgument);
  fs::remove_all(certs);
}

// grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo with
// ServerReflectionRequest{list_services: ""} (field 7), answered by
// ServerReflectionResponse{list_services_response (6): ListServiceResponse{service (1):
// ServiceResponse{name (1)}}}.
std::vector<std::string> ReflectionListServices(const std::shared_ptr<grpc::Channel>& channel, grpc::Status* status) {
  grpc::GenericStub stub(channel);
  grpc::CompletionQueue cq;
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
  auto next = [&] {
    void* tag;
    bool ok = false;
    return cq.Next(&tag, &ok) && ok;
  };
  std::unique_ptr<grpc::GenericClientAsyncReaderWriter> call =
      stub.PrepareCall(&ctx, "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo", &cq);
  std::vector<std::string> names;
  call->StartCall(reinterpret_cast<void*>(1));
  bool ok = next();
  if (ok) {
    const char request[] = {0x3a, 0x00};  // field 7, length-delimited, ""
    grpc::Slice slice(request, sizeof(request));
    grpc::ByteBuffer buffer(&slice, 1);
    call->Write(buffer, reinterpret_cast<void*>(2));
    ok = next();
  }
  if (ok) {
    call->WritesDone(reinterpret_cast<void*>(3));
    ok = next();
  }
  grpc::ByteBuffer reply;
  if (ok) {
    call->Read(&reply, reinterpret_cast<void*>(4));
    ok = next();
  }
  if (ok) {
    std::vector<grpc::Slice> slices;
    (void)reply.Dump(&slices);
    std::string bytes;
    for (const grpc::Slice& s : slices) bytes.append(reinterpret_cast<const char*>(s.begin()), s.size());
    google::protobuf::UnknownFieldSet response;
    if (response.ParseFromString(bytes)) {
      for (int i = 0; i < response.field_count(); ++i) {
        const google::protobuf::UnknownField& f = response.field(i);
        if (f.number() != 6 || f.type() != google::protobuf::UnknownField::TYPE_LENGTH_DELIMITED) continue;
        google::protobuf::UnknownFieldSet list;
        if (!list.ParseFromString(f.length_delimited())) continue;
        for (int j = 0; j < list.field_count(); ++j) {
          if (list.field(j).number() != 1) continue;
          google::protobuf::UnknownFieldSet service;
          if (!service.ParseFromString(list.field(j).length_delimited())) continue;
          for (int k = 0; k < service.field_count(); ++k) {
            if (service.field(k).number() == 1) names.push_back(service.field(k).length_delimited());
          }
        }
      }
    }
  }
  call->Finish(status, reinterpret_cast<void*>(5));
  next();
  cq.Shutdown();
  void* tag;
  bool drained_ok;
  while (cq.Next(&tag, &drained_ok)) {
  }
  return names;
}

TEST_F(TransportTest, ReflectionListsTheStreetsimServices) {
  StartServer();
  grpc::Status status;
  const std::vector<std::string> names = ReflectionListServices(client_->channel(), &status);
  EXPECT_TRUE(status.ok()) << status.error_code() << " " << status.error_message();
  for (const char* want : {"streetsim.v1.ServerInfoService", "streetsim.v1.SceneService", "streetsim.v1.RenderService",
                           "streetsim.v1.SessionService", "streetsim.v1.TrainingService", "grpc.health.v1.Health"}) {
    EXPECT_NE(std::find(names.begin(), names.end(), want), names.end()) << want << " not in the reflection list";
  }
}

TEST_F(TransportTest, ReflectionStaysOpenWithATokenConfigured) {
  const std::string token_file = state_dir_ + "/token";
  std::ofstream(token_file) << "tok\n";
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.auth_token_file = token_file;
  StartServer(o, "");
  grpc::Status status;
  const std::vector<std::string> names = ReflectionListServices(client_->channel(), &status);
  EXPECT_TRUE(status.ok()) << status.error_message();
  EXPECT_NE(std::find(names.begin(), names.end(), "streetsim.v1.RenderService"), names.end());
}

TEST_F(TransportTest, RenderQueueFloodGetsResourceExhausted) {
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.limits.max_queued_renders = 1;
  o.debug_render_delay_ms = 300;
  StartServer(o);
  ASSERT_TRUE(client_->LoadScene("timed", true).ok());
  v1::RenderRequest req;
  req.set_scene("timed");
  req.set_time_us(100000);
  req.add_sensors()->set_sensor_id("cam_front");
  req.mutable_outputs()->set_rgb(true);
  constexpr int kRequests = 8;
  std::atomic<int> ok{0}, exhausted{0}, other{0};
  std::vector<std::thread> threads;
  for (int i = 0; i < kRequests; ++i) {
    threads.emplace_back([&] {
      absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
      if (r.ok()) {
        ++ok;
      } else if (r.status().code() == absl::StatusCode::kResourceExhausted) {
        ++exhausted;
      } else {
        ++other;
        ADD_FAILURE() << r.status();
      }
    });
  }
  for (std::thread& t : threads) t.join();
  EXPECT_GE(ok.load(), 1);
  EXPECT_GE(exhausted.load(), 1);
  EXPECT_EQ(other.load(), 0);
  EXPECT_EQ(ok + exhausted, kRequests);
  // Still serving afterwards.
  absl::StatusOr<v1::RenderResponse> after = client_->Render(req);
  ASSERT_TRUE(after.ok()) << after.status();
  absl::StatusOr<v1::ServerInfo> info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->limits().max_queued_renders(), 1);
}

}  // namespace
}  // namespace streetsim::testing
