// SessionService: atomic steps, idempotent retry, deadline leaving the session unchanged, fork,
// Drive, limits and leases.
#include <limits>
#include <thread>

#include <grpcpp/client_context.h>

#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

class SessionTest : public ServerTest {
 protected:
  v1::CreateSessionRequest TimedSession() {
    v1::CreateSessionRequest req;
    req.set_scene("timed");
    req.set_step_dt_us(100000);
    req.set_seed(7);
    return req;
  }
  v1::StepRequest StepAt(const std::string& id, int64_t index, double x_m) {
    v1::StepRequest req;
    req.set_session_id(id);
    req.set_step_index(index);
    Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
    ego.translation().x() = x_m;
    *req.mutable_t_world_from_ego() = client::ToPose(ego);
    return req;
  }
};

TEST_F(SessionTest, StepsAdvanceAndRetryIsIdempotent) {
  StartServer();
  absl::StatusOr<v1::Session> s = client_->CreateSession(TimedSession());
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->last_step_index(), -1);
  EXPECT_EQ(s->rig().cameras_size(), 2);
  EXPECT_EQ(s->seed(), 7u);
  std::string digest1;
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<v1::StepResponse> r = client_->Step(StepAt(s->session_id(), i, i * 1.0));
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_EQ(r->step_index(), i);
    EXPECT_EQ(r->time_us(), i * 100000);
    EXPECT_EQ(r->frames_size(), 2);  // every sensor, atomically
    if (i == 1) digest1 = r->content_digest();
  }
  // Repeating the last index returns the cached response without advancing, even with another pose.
  absl::StatusOr<v1::StepResponse> again = client_->Step(StepAt(s->session_id(), 2, 99.0));
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->step_index(), 2);
  EXPECT_NEAR(again->t_world_from_ego().translation_m().x(), 2.0, 1e-12);
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 2);
  // Out of order: FAILED_PRECONDITION, nothing changes.
  EXPECT_EQ(client_->Step(StepAt(s->session_id(), 1, 0)).status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(client_->Step(StepAt(s->session_id(), 5, 0)).status().code(), absl::StatusCode::kFailedPrecondition);
  // Bad pose: INVALID_ARGUMENT, nothing changes.
  v1::StepRequest bad = StepAt(s->session_id(), 3, 0);
  bad.mutable_t_world_from_ego()->mutable_rotation()->set_w(2);
  EXPECT_EQ(client_->Step(bad).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 2);
  // Trajectory ego input: the server follows it (at step 3, t = 0.3 s -> x = 3 m).
  v1::StepRequest traj;
  traj.set_session_id(s->session_id());
  traj.set_step_index(3);
  for (int k = 0; k < 2; ++k) {
    v1::TimedPose* p = traj.mutable_trajectory()->add_poses();
    p->set_time_us(k * 1000000);
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.translation().x() = k * 10.0;
    *p->mutable_t_world_from_ego() = client::ToPose(T);
  }
  absl::StatusOr<v1::StepResponse> tr = client_->Step(traj);
  ASSERT_TRUE(tr.ok()) << tr.status();
  EXPECT_NEAR(tr->t_world_from_ego().translation_m().x(), 3.0, 1e-9);
  // Unknown session.
  EXPECT_EQ(client_->Step(StepAt("s-nope", 0, 0)).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(SessionTest, StepsPastTheSceneEndAreOutOfRange) {
  StartServer();
  v1::CreateSessionRequest req = TimedSession();
  req.set_start_time_us(1900000);
  absl::StatusOr<v1::Session> s = client_->CreateSession(req);
  ASSERT_TRUE(s.ok()) << s.status();
  ASSERT_TRUE(client_->Step(StepAt(s->session_id(), 0, 0)).ok());
  ASSERT_TRUE(client_->Step(StepAt(s->session_id(), 1, 0)).ok());  // 2.0 s: the last instant
  EXPECT_EQ(client_->Step(StepAt(s->session_id(), 2, 0)).status().code(), absl::StatusCode::kOutOfRange);
  req.set_start_time_us(3000000);
  EXPECT_EQ(client_->CreateSession(req).status().code(), absl::StatusCode::kOutOfRange);
}

TEST_F(SessionTest, DeadlineExpiryLeavesSessionUnchanged) {
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.debug_render_delay_ms = 400;
  StartServer(o);
  absl::StatusOr<v1::Session> s = client_->CreateSession(TimedSession());
  ASSERT_TRUE(s.ok());
  ASSERT_TRUE(client_->Step(StepAt(s->session_id(), 0, 0)).ok());
  // 100 ms deadline on a 400 ms render.
  absl::StatusOr<v1::StepResponse> late = client_->Step(StepAt(s->session_id(), 1, 5.0), 0.1);
  EXPECT_EQ(late.status().code(), absl::StatusCode::kDeadlineExceeded);
  std::this_thread::sleep_for(std::chrono::milliseconds(150));  // let the server notice and give up
  absl::StatusOr<v1::Session> after = client_->GetSession(s->session_id());
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->last_step_index(), 0);
  EXPECT_NEAR(after->t_world_from_ego().translation_m().x(), 0.0, 1e-12);
  // The retry of the same step succeeds and commits.
  absl::StatusOr<v1::StepResponse> retry = client_->Step(StepAt(s->session_id(), 1, 5.0));
  ASSERT_TRUE(retry.ok()) << retry.status();
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 1);
  // Cancelled mid-step by the client: unchanged too.
  grpc::ClientContext ctx;
  client_->Prepare(&ctx);
  v1::StepResponse resp;
  std::thread canceller([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ctx.TryCancel();
  });
  grpc::Status st = client_->session_stub()->Step(&ctx, StepAt(s->session_id(), 2, 7.0), &resp);
  canceller.join();
  EXPECT_EQ(st.error_code(), grpc::StatusCode::CANCELLED);
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 1);
}

TEST_F(SessionTest, ForkBranchesIndependently) {
  StartServer();
  absl::StatusOr<v1::Session> a = client_->CreateSession(TimedSession());
  ASSERT_TRUE(a.ok());
  ASSERT_TRUE(client_->Step(StepAt(a->session_id(), 0, 1.0)).ok());
  absl::StatusOr<v1::Session> b = client_->ForkSession(a->session_id());
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_NE(b->session_id(), a->session_id());
  EXPECT_EQ(b->forked_from(), a->session_id());
  EXPECT_EQ(b->last_step_index(), 0);
  // Both continue from step 1 independently; same pose -> same frame, other pose -> other frame.
  absl::StatusOr<v1::StepResponse> ra = client_->Step(StepAt(a->session_id(), 1, 2.0));
  absl::StatusOr<v1::StepResponse> rb = client_->Step(StepAt(b->session_id(), 1, 2.0));
  ASSERT_TRUE(ra.ok() && rb.ok());
  EXPECT_EQ(ra->content_digest(), rb->content_digest());
  absl::StatusOr<v1::StepResponse> rb2 = client_->Step(StepAt(b->session_id(), 2, 4.0));
  ASSERT_TRUE(rb2.ok());
  EXPECT_EQ(client_->GetSession(a->session_id())->last_step_index(), 1);
  EXPECT_EQ(client_->ForkSession("s-nope").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(SessionTest, DriveStreamHasStepSemantics) {
  StartServer();
  absl::StatusOr<v1::Session> s = client_->CreateSession(TimedSession());
  ASSERT_TRUE(s.ok());
  grpc::ClientContext ctx;
  client_->Prepare(&ctx);
  auto stream = client_->session_stub()->Drive(&ctx);
  v1::StepResponse resp;
  for (int i = 0; i < 3; ++i) {
    ASSERT_TRUE(stream->Write(StepAt(s->session_id(), i, i * 0.5)));
    ASSERT_TRUE(stream->Read(&resp));
    EXPECT_EQ(resp.step_index(), i);
    EXPECT_EQ(resp.frames_size(), 2);
  }
  ASSERT_TRUE(stream->Write(StepAt(s->session_id(), 2, 0)));  // a retry: cached
  ASSERT_TRUE(stream->Read(&resp));
  EXPECT_EQ(resp.step_index(), 2);
  ASSERT_TRUE(stream->Write(StepAt(s->session_id(), 7, 0)));  // wrong index ends the stream
  EXPECT_FALSE(stream->Read(&resp));
  EXPECT_EQ(stream->Finish().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 2);
}

TEST_F(SessionTest, LimitsIdempotentCreateAndLeases) {
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.limits.max_sessions = 2;
  o.limits.session_lease_ms = 600;
  StartServer(o);
  v1::CreateSessionRequest req = TimedSession();
  req.set_request_id("r1");
  absl::StatusOr<v1::Session> a = client_->CreateSession(req);
  absl::StatusOr<v1::Session> a2 = client_->CreateSession(req);
  ASSERT_TRUE(a.ok() && a2.ok());
  EXPECT_EQ(a->session_id(), a2->session_id());
  // The same request_id for a different request is an error, not the earlier session.
  v1::CreateSessionRequest other = req;
  other.set_seed(req.seed() + 1);
  absl::StatusOr<v1::Session> reused = client_->CreateSession(other);
  EXPECT_EQ(reused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(reused.status().message().find("request_id 'r1' was already used for a different session"),
            std::string::npos) << reused.status();
  req.set_request_id("r2");
  ASSERT_TRUE(client_->CreateSession(req).ok());
  req.set_request_id("r3");
  EXPECT_EQ(client_->CreateSession(req).status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(client_->ForkSession(a->session_id()).status().code(), absl::StatusCode::kResourceExhausted);
  ASSERT_TRUE(client_->CloseSession(a->session_id()).ok());
  ASSERT_TRUE(client_->CreateSession(req).ok());
  // Leases: after 600 ms without calls the sessions are gone and their slots free.
  std::this_thread::sleep_for(std::chrono::milliseconds(800));
  EXPECT_EQ(client_->GetSession(a2->session_id()).status().code(), absl::StatusCode::kNotFound);
  req.set_request_id("r4");
  EXPECT_TRUE(client_->CreateSession(req).ok());
  // Bad create inputs.
  v1::CreateSessionRequest bad = TimedSession();
  bad.set_scene("nope");
  EXPECT_EQ(client_->CreateSession(bad).status().code(), absl::StatusCode::kNotFound);
  // An absurd name is echoed shortened (a whole one would overflow the client's metadata limit).
  bad.set_scene(std::string(200000, 'x') + "\n");
  absl::Status huge = client_->CreateSession(bad).status();
  EXPECT_EQ(huge.code(), absl::StatusCode::kNotFound) << huge;
  EXPECT_LT(huge.message().size(), 300u) << huge.message().size();
  EXPECT_NE(huge.message().find("(200001 bytes)"), std::string::npos) << huge.message();
  EXPECT_EQ(client_->GetSession(std::string(100000, 's')).status().code(), absl::StatusCode::kNotFound);
  EXPECT_LT(client_->GetSession(std::string(100000, 's')).status().message().size(), 300u);
  bad = TimedSession();
  bad.set_step_dt_us(-1);
  EXPECT_EQ(client_->CreateSession(bad).status().code(), absl::StatusCode::kInvalidArgument);
  bad = TimedSession();
  bad.add_sensors()->set_sensor_id("cam_nope");
  EXPECT_EQ(client_->CreateSession(bad).status().code(), absl::StatusCode::kNotFound);
}

TEST_F(SessionTest, StepTimesThatLeaveInt64AreOutOfRange) {
  StartServer(TestOptions(data_root_, state_dir_));
  // A static scene takes any time: the session starts 50 ms before the end of int64 microseconds.
  v1::CreateSessionRequest req;
  req.set_scene("street");
  req.set_step_dt_us(100000);
  req.set_start_time_us(std::numeric_limits<int64_t>::max() - 50000);
  req.add_sensors()->set_sensor_id("cam_front");
  req.mutable_sensors(0)->set_width(64);
  req.mutable_sensors(0)->set_height(32);
  absl::StatusOr<v1::Session> s = client_->CreateSession(req);
  ASSERT_TRUE(s.ok()) << s.status();
  ASSERT_TRUE(client_->Step(StepAt(s->session_id(), 0, 0.0)).ok());
  absl::StatusOr<v1::StepResponse> next = client_->Step(StepAt(s->session_id(), 1, 1.0));
  EXPECT_EQ(next.status().code(), absl::StatusCode::kOutOfRange) << next.status();
  // The step did not happen: the session still expects step 1.
  absl::StatusOr<v1::Session> info = client_->GetSession(s->session_id());
  ASSERT_TRUE(info.ok());
  EXPECT_EQ(info->last_step_index(), 0);
}

}  // namespace
}  // namespace streetsim::testing
