// Closed-loop sessions: per-session clock, single writer, atomic steps, cached last response
// (idempotent retry), leases, forks.
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/actors/actor_edits.h"
#include "server/render_core.h"
#include "server/scene_manifest.h"
#include "server/service_deps.h"
#include "streetsim/v1/session.pb.h"

namespace streetsim::server {

class SessionManager {
 public:
  explicit SessionManager(ServiceDeps* deps) : deps_(deps) {}

  absl::StatusOr<v1::Session> Create(const v1::CreateSessionRequest& req);
  absl::StatusOr<v1::Session> Get(const std::string& id);
  std::vector<v1::Session> List();
  absl::Status Close(const std::string& id);
  absl::StatusOr<v1::Session> Fork(const std::string& id);
  // Atomic: on any error (including cancel / deadline) the session is unchanged.
  absl::StatusOr<std::shared_ptr<const v1::StepResponse>> Step(const v1::StepRequest& req,
                                                                const CancelCheck& cancel);
  int size();

 private:
  struct Committed {
    int64_t last_step_index = -1;
    int64_t time_us = 0;
    Eigen::Isometry3d T_world_from_ego = Eigen::Isometry3d::Identity();
    std::shared_ptr<const v1::StepResponse> last_response;
    // The actors' edits in force (CreateSession's, replaced by a step that sets its own);
    // committed with the step that set them.
    std::vector<actors::ActorEdit> actor_edits;
  };
  struct Session {
    std::string id;
    std::string scene;
    std::shared_ptr<const SceneManifest> manifest;
    std::vector<RigCamera> cameras;
    v1::OutputSpec outputs;
    std::optional<v1::LidarRequest> lidar;  // every step's LiDAR (validated at creation)
    int64_t start_time_us = 0;
    int64_t step_dt_us = 0;
    uint64_t seed = 0;
    std::string forked_from;
    std::string request_fingerprint;  // CreateSession's request without its request_id
    std::mutex step_mu;  // one step at a time
    std::mutex mu;       // guards state and lease
    Committed state;
    std::chrono::steady_clock::time_point lease_expiry;
  };

  std::shared_ptr<Session> FindLocked(const std::string& id);
  void PurgeExpiredLocked();
  std::string NewIdLocked();
  absl::Status UnknownSession(const std::string& id) const;
  v1::Session Describe(Session& s);
  void Renew(Session& s);

  ServiceDeps* deps_;
  std::mutex mu_;
  std::map<std::string, std::shared_ptr<Session>> sessions_;
  std::map<std::string, std::string> by_request_id_;
  uint64_t next_id_ = 1;
};

}  // namespace streetsim::server
