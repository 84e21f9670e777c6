// Bounded load benchmark: N sessions x M steps on loopback against an in-process server (real
// gRPC over 127.0.0.1), one client thread per session. Prints p50/p99 step latency, throughput
// and the server's RSS before/after. Usage:
//   server_load_bench [--sessions N] [--steps M] [--width W] [--height H] [--gaussians G]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <thread>

#include "server/info_and_scene_services.h"
#include "tests/server/server_fixture.h"

using namespace streetsim;
namespace v1 = streetsim::v1;

int main(int argc, char** argv) {
  int sessions = 4, steps = 50, width = 320, height = 96, gaussians = 100000;
  for (int i = 1; i + 1 < argc; i += 2) {
    const int v = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--sessions")) sessions = v;
    else if (!std::strcmp(argv[i], "--steps")) steps = v;
    else if (!std::strcmp(argv[i], "--width")) width = v;
    else if (!std::strcmp(argv[i], "--height")) height = v;
    else if (!std::strcmp(argv[i], "--gaussians")) gaussians = v;
  }
  const std::string root = streetsim::testing::MakeTempDir("bench_data");
  const std::string state = streetsim::testing::MakeTempDir("bench_state");
  SyntheticStreetOptions so;
  so.num_gaussians = gaussians;
  if (!WriteGaussianPly(MakeSyntheticStreet(so), root + "/street.ply").ok()) return 1;
  server::ServerOptions o = streetsim::testing::TestOptions(root, state);
  o.limits.max_sessions = std::max(16, sessions);
  o.limits.max_queued_renders = std::max(8, sessions);
  auto srv = server::Server::Start(o);
  if (!srv.ok()) return 1;
  auto c0 = client::Client::Connect({.target = (*srv)->address()});
  if (!(*c0)->LoadScene("street", true).ok()) return 1;
  const int64_t rss_before = server::CurrentRssBytes();

  std::vector<std::vector<double>> lat(sessions);
  std::vector<std::thread> threads;
  std::atomic<int> errors{0};
  const auto t0 = std::chrono::steady_clock::now();
  for (int s = 0; s < sessions; ++s) {
    threads.emplace_back([&, s] {
      auto c = client::Client::Connect({.target = (*srv)->address()});
      v1::CreateSessionRequest req;
      req.set_scene("street");
      auto* sensor = req.add_sensors();
      sensor->set_sensor_id("cam_front");
      sensor->set_width(width);
      sensor->set_height(height);
      auto session = (*c)->CreateSession(req);
      if (!session.ok()) { ++errors; return; }
      for (int k = 0; k < steps; ++k) {
        v1::StepRequest step;
        step.set_session_id(session->session_id());
        step.set_step_index(k);
        Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
        ego.translation() = Eigen::Vector3d(0.5 * k, 0.3 * s, 1.65);
        *step.mutable_t_world_from_ego() = client::ToPose(ego);
        const auto a = std::chrono::steady_clock::now();
        if (!(*c)->Step(step).ok()) ++errors;
        lat[s].push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - a).count());
      }
      (void)(*c)->CloseSession(session->session_id());
    });
  }
  for (auto& t : threads) t.join();
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  const int64_t rss_after = server::CurrentRssBytes();
  std::vector<double> all;
  for (auto& l : lat) all.insert(all.end(), l.begin(), l.end());
  std::sort(all.begin(), all.end());
  auto pct = [&](double q) { return all.empty() ? 0.0 : all[std::min(all.size() - 1, size_t(q * all.size()))]; };
  std::printf("| sessions | steps each | image | Gaussians | p50 ms | p99 ms | max ms | steps/s | errors | RSS before MiB | RSS after MiB |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::printf("| %d | %d | %dx%d RAW | %d | %.1f | %.1f | %.1f | %.1f | %d | %.1f | %.1f |\n", sessions, steps, width,
              height, gaussians, pct(0.5), pct(0.99), all.empty() ? 0 : all.back(), all.size() / wall_s,
              errors.load(), rss_before / 1048576.0, rss_after / 1048576.0);
  srv->reset();
  std::filesystem::remove_all(root);
  std::filesystem::remove_all(state);
  return errors.load() ? 1 : 0;
}
