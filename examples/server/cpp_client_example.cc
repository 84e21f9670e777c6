// C++ client example: server info, the scene list, then a 10-step closed loop that drives the
// ego forward and prints each step's latency and the free depth straight ahead; from step 5 the
// scene's first actor, if it has actors, is removed (docs/actors.md).
//   build/bin/streetsim_client_example 127.0.0.1:50051 SCENE
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <optional>

#include "client/cpp/streetsim_client.h"

namespace v1 = streetsim::v1;
using streetsim::client::Client;

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: %s HOST:PORT SCENE\n", argv[0]);
    return 2;
  }
  auto client = Client::Connect({.target = argv[1]});
  if (!client.ok() || !(*client)->WaitForReady(10).ok()) {
    std::fprintf(stderr, "cannot reach %s\n", argv[1]);
    return 1;
  }
  auto info = (*client)->GetServerInfo();
  if (!info.ok()) {
    std::fprintf(stderr, "%s\n", std::string(info.status().message()).c_str());
    return 1;
  }
  std::printf("server api %s on %s\n", info->api_version().c_str(), info->device().c_str());
  v1::CreateSessionRequest create;
  create.set_scene(argv[2]);
  create.mutable_outputs()->set_depth(true);
  create.mutable_outputs()->set_alpha(true);
  auto session = (*client)->CreateSession(create);
  if (!session.ok()) {
    std::fprintf(stderr, "%s\n", std::string(session.status().message()).c_str());
    return 1;
  }
  Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
  ego.translation().z() = 1.65;
  std::optional<v1::ActorEdits> pending_edits;
  for (int k = 0; k < 10; ++k) {
    v1::StepRequest step;
    step.set_session_id(session->session_id());
    step.set_step_index(k);
    *step.mutable_t_world_from_ego() = streetsim::client::ToPose(ego);
    if (pending_edits) {
      *step.mutable_actor_edits() = *pending_edits;  // replaces the session's edits from this step
      pending_edits.reset();
    }
    const auto t0 = std::chrono::steady_clock::now();
    auto r = (*client)->Step(step);
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    if (!r.ok()) {
      std::fprintf(stderr, "step %d: %s\n", k, std::string(r.status().message()).c_str());
      return 1;
    }
    auto depth = streetsim::client::DecodeImage(r->frames(0).depth());
    auto alpha = streetsim::client::DecodeImage(r->frames(0).alpha());
    const int w = depth->width, h = depth->height;
    const size_t c = size_t(h / 2) * w + w / 2;
    const float free = alpha->f32[c] > 0.5f ? depth->f32[c] / alpha->f32[c] : -1.0f;
    std::printf("step %d: %.1f ms, free depth ahead %.2f m, %s\n", k, ms, free, r->content_digest().c_str());
    ego.translation().x() += 0.5;
    // From step 5, the scene's first actor (docs/actors.md), if it has any, leaves the scene.
    if (k == 4) {
      auto scene = (*client)->GetScene(argv[2]);
      if (scene.ok() && scene->actors_size() > 0) {
        pending_edits.emplace();
        *pending_edits->add_edits() = streetsim::client::RemoveActor(scene->actors(0).actor_id());
      }
    }
  }
  (void)(*client)->CloseSession(session->session_id());
  return 0;
}
