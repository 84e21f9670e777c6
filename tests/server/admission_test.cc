// Admission before work (server/admission.h), the fair render queue (server/fair_gate.h) and
// renders that stop for their caller (RenderOptions::should_stop).
#include <atomic>
#include <chrono>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

#include "render/engine.h"
#include "scene/gaussians/synthetic_street.h"
#include "server/admission.h"
#include "server/fair_gate.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

using server::FairGate;

// Waits until the gate counts `n` (holder + waiting).
void WaitForInFlight(const FairGate& gate, int n) {
  for (int i = 0; i < 2000 && gate.in_flight() != n; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(1));
  ASSERT_EQ(gate.in_flight(), n);
}

TEST(FairGate, ServesWaitingClientsRoundRobin) {
  FairGate gate(8, 8);
  FairGate::Pass holder;
  ASSERT_TRUE(gate.Enter("x", nullptr, &holder).ok());
  std::mutex mu;
  std::vector<std::string> order;
  std::vector<std::thread> threads;
  // Client a queues three renders before b and c queue one each.
  int queued = 1;
  for (const char* who : {"a1", "a2", "a3", "b1", "c1"}) {
    threads.emplace_back([&, who] {
      FairGate::Pass pass;
      ASSERT_TRUE(gate.Enter(std::string(1, who[0]), nullptr, &pass).ok());
      std::lock_guard<std::mutex> l(mu);
      order.push_back(who);
    });
    WaitForInFlight(gate, ++queued);
  }
  holder = FairGate::Pass();
  for (std::thread& t : threads) t.join();
  EXPECT_EQ(order, (std::vector<std::string>{"a1", "b1", "c1", "a2", "a3"}));
  EXPECT_EQ(gate.in_flight(), 0);
}

TEST(FairGate, BoundsTheQueueInAllAndPerClient) {
  FairGate gate(4, 2);
  FairGate::Pass holder;
  ASSERT_TRUE(gate.Enter("x", nullptr, &holder).ok());
  std::vector<std::thread> threads;
  const auto wait_in_queue = [&](const char* client) {
    threads.emplace_back([&gate, client] {
      FairGate::Pass pass;
      EXPECT_TRUE(gate.Enter(client, nullptr, &pass).ok());
    });
  };
  for (const char* client : {"a", "a", "b"}) wait_in_queue(client);
  WaitForInFlight(gate, 4);
  FairGate::Pass refused;
  absl::Status a = gate.Enter("a", nullptr, &refused);  // a's share (2) is full, the queue is not
  EXPECT_EQ(a.code(), absl::StatusCode::kResourceExhausted) << a;
  EXPECT_NE(a.message().find("this client"), std::string::npos) << a;
  wait_in_queue("c");
  WaitForInFlight(gate, 5);
  absl::Status d = gate.Enter("d", nullptr, &refused);  // the whole queue (4) is full
  EXPECT_EQ(d.code(), absl::StatusCode::kResourceExhausted) << d;
  EXPECT_NE(d.message().find("queue full"), std::string::npos) << d;
  holder = FairGate::Pass();
  for (std::thread& t : threads) t.join();
  EXPECT_EQ(gate.in_flight(), 0);
}

TEST(FairGate, ACancelledWaiterLeavesTheQueue) {
  FairGate gate(4, 4);
  FairGate::Pass holder;
  ASSERT_TRUE(gate.Enter("x", nullptr, &holder).ok());
  std::atomic<bool> cancel{false};
  absl::Status waited;
  std::thread a([&] {
    FairGate::Pass pass;
    waited = gate.Enter("a", [&] { return cancel ? absl::CancelledError("gone") : absl::OkStatus(); }, &pass);
  });
  WaitForInFlight(gate, 2);
  cancel = true;
  a.join();
  EXPECT_EQ(waited.code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(gate.in_flight(), 1);
  holder = FairGate::Pass();
  FairGate::Pass next;
  EXPECT_TRUE(gate.Enter("b", nullptr, &next).ok());
}

v1::PinholeIntrinsics BigIntrinsics() {
  v1::PinholeIntrinsics k;
  k.set_width(4096);
  k.set_height(4096);
  k.set_fx(2000);
  k.set_fy(2000);
  k.set_cx(2047.5);
  k.set_cy(2047.5);
  return k;
}

server::CameraView View(int w, int h) {
  server::CameraView v;
  v.sensor_id = "cam";
  v.intrinsics.width = w;
  v.intrinsics.height = h;
  v.intrinsics.fx = v.intrinsics.fy = w;
  v.intrinsics.cx = w / 2.0;
  v.intrinsics.cy = h / 2.0;
  return v;
}

TEST(Admission, CountsPixelsRaysAndRawBytes) {
  v1::OutputSpec outputs;
  outputs.set_rgb(true);                                       // raw: 3 B
  outputs.set_depth(true);
  outputs.set_depth_encoding(v1::DEPTH_ENCODING_PNG16);        // compressed: no lower bound
  outputs.set_alpha(true);                                     // raw float: 4 B
  server::LidarJob lidar;
  lidar.model.beam_elevation_deg.assign(64, 0.0);
  lidar.model.columns = 1024;
  const server::RenderCost cost = server::EstimateRenderCost({View(100, 50), View(100, 50)}, outputs, &lidar);
  EXPECT_EQ(cost.pixels, 10000);
  EXPECT_EQ(cost.lidar_rays, 64 * 1024);
  EXPECT_EQ(cost.min_response_bytes, 10000 * (3 + 4) + 64 * 1024 * 12);

  server::ServerLimits limits;
  EXPECT_TRUE(server::AdmitRender(cost, limits).ok());
  limits.max_request_pixels = 9999;
  EXPECT_EQ(server::AdmitRender(cost, limits).code(), absl::StatusCode::kResourceExhausted);
  limits = {};
  limits.max_message_bytes = cost.min_response_bytes - 1;
  EXPECT_EQ(server::AdmitRender(cost, limits).code(), absl::StatusCode::kResourceExhausted);
  limits = {};
  limits.max_lidar_rays = 64 * 1024 - 1;
  EXPECT_EQ(server::AdmitRender(cost, limits).code(), absl::StatusCode::kResourceExhausted);
}

class AdmissionServerTest : public ServerTest {};

// A renderer that takes 5 s per render: a request refused before rendering comes back long before.
TEST_F(AdmissionServerTest, RefusesOversizedRequestsBeforeRendering) {
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.debug_render_delay_ms = 5000;
  StartServer(o);
  struct Case {
    const char* what;
    int sensors;
    bool raw;
    const char* says;
  };
  for (const Case& c : {Case{"two 4096x4096 cameras", 2, false, "pixels"},
                        Case{"one 4096x4096 camera, raw RGB + depth + alpha", 1, true, "at least"}}) {
    v1::RenderRequest req;
    req.set_scene("street");
    *req.mutable_t_world_from_ego() = Identity();
    for (int i = 0; i < c.sensors; ++i) {
      v1::SensorRequest* s = req.add_sensors();
      s->set_sensor_id(i == 0 ? "cam_front" : "cam_extra");
      s->set_width(4096);
      s->set_height(4096);
      if (i > 0) {
        *s->mutable_intrinsics() = BigIntrinsics();
        *s->mutable_t_ego_from_sensor() = Identity();
      }
    }
    req.mutable_outputs()->set_rgb(true);
    req.mutable_outputs()->set_depth(c.raw);
    req.mutable_outputs()->set_alpha(c.raw);
    if (!c.raw) req.mutable_outputs()->set_rgb_encoding(v1::IMAGE_ENCODING_JPEG);
    const auto t0 = std::chrono::steady_clock::now();
    absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    ASSERT_FALSE(r.ok()) << c.what;
    EXPECT_EQ(r.status().code(), absl::StatusCode::kResourceExhausted) << c.what << ": " << r.status();
    EXPECT_NE(r.status().message().find(c.says), std::string::npos) << r.status();
    EXPECT_LT(s, 4.0) << c.what << " was rendered before it was refused";
  }
  // A session whose steps would all be refused is refused at creation.
  v1::CreateSessionRequest session;
  session.set_scene("street");
  for (const char* id : {"cam_front", "cam_extra"}) {
    v1::SensorRequest* s = session.add_sensors();
    s->set_sensor_id(id);
    *s->mutable_intrinsics() = BigIntrinsics();
    *s->mutable_t_ego_from_sensor() = Identity();
  }
  absl::StatusOr<v1::Session> created = client_->CreateSession(session);
  ASSERT_FALSE(created.ok());
  EXPECT_EQ(created.status().code(), absl::StatusCode::kResourceExhausted) << created.status();
  absl::StatusOr<v1::ServerInfo> info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->limits().max_request_pixels(), int64_t{4096} * 4096);
  EXPECT_EQ(info->limits().max_queued_renders_per_client(), 2);
}

TEST(StoppableRender, StopsBetweenTilesAndIsUnchangedWhenNotStopped) {
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(engine.ok()) << engine.status();
  SyntheticStreetOptions so;
  so.num_gaussians = 20000;
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(MakeSyntheticStreet(so));
  ASSERT_TRUE(scene.ok()) << scene.status();
  PinholeCamera cam;
  cam.width = 640;
  cam.height = 360;
  cam.fx = cam.fy = 500;
  cam.cx = 319.5;
  cam.cy = 179.5;
  Eigen::Matrix3d R;
  R << 0, 0, 1, -1, 0, 0, 0, -1, 0;  // looking down the street (+x), z up
  cam.T_world_from_cam.linear() = R;
  cam.T_world_from_cam.translation() = Eigen::Vector3d(0, 0, 1.6);
  RenderOptions plain;
  RenderOutput reference;
  ASSERT_TRUE((*engine)->Render(**scene, cam, plain, &reference).ok());

  RenderOptions never = plain;
  std::atomic<int> asked{0};
  never.should_stop = [&] { ++asked; return false; };
  RenderOutput same;
  ASSERT_TRUE((*engine)->Render(**scene, cam, never, &same).ok());
  EXPECT_GT(asked.load(), 10);  // asked between stages and tile batches
  EXPECT_EQ(same.rgb, reference.rgb);
  EXPECT_EQ(same.depth, reference.depth);

  RenderOptions stop = plain;
  std::atomic<int> calls{0};
  stop.should_stop = [&] { return ++calls > 3; };  // gives up during the blend
  RenderOutput partial;
  absl::Status s = (*engine)->Render(**scene, cam, stop, &partial);
  EXPECT_EQ(s.code(), absl::StatusCode::kCancelled) << s;
  EXPECT_LT(calls.load(), asked.load());  // the remaining tile batches were skipped
}

}  // namespace
}  // namespace streetsim::testing
