// A real streetsim server on 127.0.0.1 (ephemeral port) over a temporary data root, and a real
// client connected to it. No gRPC mocks.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include <gtest/gtest.h>

#include "client/cpp/streetsim_client.h"
#include "scene/gaussians/ply_io.h"
#include "scene/gaussians/synthetic_street.h"
#include "server/server.h"

namespace streetsim::testing {

namespace fs = std::filesystem;
namespace v1 = ::streetsim::v1;

inline std::string MakeTempDir(const std::string& tag) {
  std::string tmpl = (fs::temp_directory_path() / ("streetsim_" + tag + "_XXXXXX")).string();
  return mkdtemp(tmpl.data());
}

// data root:
//   street.ply                      bare static scene (default rig, 1242x375 cam_front)
//   timed/scene.ply + scene.json    time range [0, 2 s], 2 small cameras, ego trajectory along x
//   logs/fake/source.ply            a "log" for the fake init stage (tests/server/fake_init.sh)
inline std::string MakeDataRoot() {
  const std::string root = MakeTempDir("data");
  SyntheticStreetOptions o;
  o.num_gaussians = 4000;
  o.sh_degree = 1;
  const GaussianStore store = MakeSyntheticStreet(o);
  EXPECT_TRUE(WriteGaussianPly(store, root + "/street.ply").ok());
  fs::create_directories(root + "/timed");
  EXPECT_TRUE(WriteGaussianPly(store, root + "/timed/scene.ply").ok());
  std::ofstream(root + "/timed/scene.json") << R"({
    "time_range_us": [0, 2000000],
    "cameras": [
      {"sensor_id": "cam_front", "width": 128, "height": 64, "fx": 80, "fy": 80, "cx": 63.5, "cy": 31.5,
       "T_ego_from_cam": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]},
      {"sensor_id": "cam_left", "width": 96, "height": 64, "fx": 60, "fy": 60, "cx": 47.5, "cy": 31.5,
       "T_ego_from_cam": [1,0,0,0, 0,0,1,0, 0,-1,0,1.65, 0,0,0,1]}],
    "ego_trajectory": [
      {"time_us": 0, "T_world_from_ego": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]},
      {"time_us": 2000000, "T_world_from_ego": [1,0,0,20, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]})";
  fs::create_directories(root + "/logs/fake");
  EXPECT_TRUE(WriteGaussianPly(store, root + "/logs/fake/source.ply").ok());
  return root;
}

inline server::ServerOptions TestOptions(const std::string& data_root, const std::string& state_dir) {
  server::ServerOptions o;
  o.listen = "127.0.0.1:0";
  o.data_root = data_root;
  o.state_dir = state_dir;
  o.backend = Backend::kCpu;
  o.init_command = {"/bin/sh", std::string(STREETSIM_SOURCE_DIR) + "/tests/server/fake_init.sh"};
  return o;
}

// A second (third, ...) server beside a fixture's own, and a client connected to it: for tests
// that compare servers started with other options.
struct RunningServer {
  std::unique_ptr<server::Server> server;
  std::unique_ptr<client::Client> client;
};
inline RunningServer StartServerAndClient(const server::ServerOptions& options) {
  RunningServer r;
  absl::StatusOr<std::unique_ptr<server::Server>> s = server::Server::Start(options);
  EXPECT_TRUE(s.ok()) << s.status();
  if (!s.ok()) return r;
  r.server = std::move(*s);
  client::ClientOptions co;
  co.target = r.server->address();
  co.timeout_s = 60;
  absl::StatusOr<std::unique_ptr<client::Client>> c = client::Client::Connect(co);
  EXPECT_TRUE(c.ok()) << c.status();
  if (c.ok()) r.client = std::move(*c);
  return r;
}

class ServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    data_root_ = MakeDataRoot();
    state_dir_ = MakeTempDir("state");
  }
  void TearDown() override {
    client_.reset();
    server_.reset();
    std::error_code ec;
    fs::remove_all(data_root_, ec);
    fs::remove_all(state_dir_, ec);
  }
  void StartServer(server::ServerOptions options, const std::string& token = "") {
    absl::StatusOr<std::unique_ptr<server::Server>> s = server::Server::Start(options);
    ASSERT_TRUE(s.ok()) << s.status();
    server_ = std::move(*s);
    client_ = Connect(token);
  }
  void StartServer() { StartServer(TestOptions(data_root_, state_dir_)); }
  std::unique_ptr<client::Client> Connect(const std::string& token = "") {
    client::ClientOptions co;
    co.target = server_->address();
    co.token = token;
    co.timeout_s = 30;
    auto c = client::Client::Connect(co);
    EXPECT_TRUE(c.ok());
    return std::move(*c);
  }

  static v1::Pose Identity() { return client::ToPose(Eigen::Isometry3d::Identity()); }

  std::string data_root_, state_dir_;
  std::unique_ptr<server::Server> server_;
  std::unique_ptr<client::Client> client_;
};

}  // namespace streetsim::testing
