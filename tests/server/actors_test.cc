// Actors over the wire (docs/actors.md): GetScene lists them, Render, RenderTrajectory and session
// steps take edits, bad edits are INVALID_ARGUMENT, and a stale actor set is refused by name.
#include <cmath>

#include "scene/actors/actor_set.h"
#include "scene/actors/rigid_gaussians.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

// timed/ (server_fixture.h) plus a red block of 400 Gaussians 8 m ahead of the ego's start,
// in front of cam_front: actor 1, standing still over the log.
class ActorsTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    const std::string dir = data_root_ + "/timed";
    absl::StatusOr<GaussianStore> store = ReadGaussianPly(dir + "/scene.ply");
    ASSERT_TRUE(store.ok());
    const size_t first = store->size();
    const int K = store->sh_coeffs();
    store->Resize(first + 400);
    actors::Actor actor;
    actor.id = 1;
    actor.half_extent_m = Eigen::Vector3d(1.2, 0.9, 0.7);
    for (size_t j = 0; j < 400; ++j) {
      const size_t i = first + j;
      const float x = 7 + 0.1f * static_cast<float>(j % 20), y = -0.8f + 0.08f * static_cast<float>(j / 20),
                  z = 0.6f + 0.04f * static_cast<float>(j % 7);
      store->means[i * 3] = x;
      store->means[i * 3 + 1] = y;
      store->means[i * 3 + 2] = z;
      for (int a = 0; a < 3; ++a) store->log_scales[i * 3 + a] = std::log(0.08f);
      store->rotations[i * 4] = 1;
      store->rotations[i * 4 + 1] = store->rotations[i * 4 + 2] = store->rotations[i * 4 + 3] = 0;
      store->opacity_logits[i] = 4;
      std::fill_n(&store->sh[i * K * 3], K * 3, 0.0f);
      store->sh[i * K * 3] = 1.5f;  // red
      store->sh[i * K * 3 + 1] = store->sh[i * K * 3 + 2] = -1.5f;
      actor.body_rows.push_back(static_cast<uint32_t>(i));
    }
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.translation() = Eigen::Vector3d(8, 0, 1);
    actor.trajectory = {{0, T}, {2'000'000, T}};
    actor.reference_time_us = 0;
    actor.gaussians.sh_degree = store->sh_degree;
    actors::AppendRows(*store, actor.body_rows.data(), actor.body_rows.size(), &actor.gaussians);
    actors::TransformGaussians(T.inverse(), &actor.gaussians);
    ASSERT_TRUE(WriteGaussianPly(*store, dir + "/scene.ply").ok());
    actors::ActorSet set;
    set.scene_gaussians = store->size();
    set.sh_degree = store->sh_degree;
    set.scene_checksum = *actors::SceneChecksum(dir + "/scene.ply");
    set.actors.push_back(std::move(actor));
    ASSERT_TRUE(actors::WriteActorSet(set, dir).ok());
    StartServer();
  }

  static v1::ActorEdit Remove(int id) { return client::RemoveActor(id); }
  static v1::ActorEdit MoveTo(int id, double y_m, v1::ActorEditKind kind = v1::ACTOR_EDIT_MOVE) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.translation() = Eigen::Vector3d(8, y_m, 1);
    v1::ActorEdit e = kind == v1::ACTOR_EDIT_INSERT ? client::InsertActor(id, {{0, T}}) : client::MoveActor(id, {{0, T}});
    e.set_kind(kind);  // the bad-edit cases ask for other kinds with a trajectory
    return e;
  }
  absl::StatusOr<v1::RenderResponse> RenderAt(int64_t time_us, const std::vector<v1::ActorEdit>& edits,
                                              const std::string& scene = "timed", const v1::Pose* ego = nullptr) {
    v1::RenderRequest req;
    req.set_scene(scene);
    req.set_time_us(time_us);
    if (ego != nullptr) *req.mutable_t_world_from_ego() = *ego;
    req.add_sensors()->set_sensor_id("cam_front");
    for (const v1::ActorEdit& e : edits) *req.add_actor_edits() = e;
    return client_->Render(req);
  }
};

TEST_F(ActorsTest, GetSceneListsTheActors) {
  absl::StatusOr<v1::Scene> scene = client_->LoadScene("timed", true);
  ASSERT_TRUE(scene.ok()) << scene.status();
  scene = client_->GetScene("timed");
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->actors_size(), 1);
  EXPECT_EQ(scene->actors(0).actor_id(), 1);
  EXPECT_EQ(scene->actors(0).num_gaussians(), 400u);
  EXPECT_EQ(scene->actors(0).end_time_us(), 2'000'000);
  EXPECT_NEAR(scene->actors(0).half_extent_m().x(), 1.2, 1e-9);
  ASSERT_EQ(scene->actors(0).trajectory_size(), 2);
  EXPECT_NEAR(scene->actors(0).trajectory(1).t_world_from_actor().translation_m().x(), 8, 1e-9);
  absl::StatusOr<std::vector<v1::Scene>> all = client_->ListScenes();
  ASSERT_TRUE(all.ok());
  for (const v1::Scene& s : *all) {
    if (s.name() == "timed") EXPECT_EQ(s.actors(0).trajectory_size(), 0) << "trajectories in GetScene only";
  }
}

TEST_F(ActorsTest, RenderAndTrajectoryTakeEdits) {
  const absl::StatusOr<v1::RenderResponse> plain = RenderAt(500'000, {});
  const absl::StatusOr<v1::RenderResponse> removed = RenderAt(500'000, {Remove(1)});
  const absl::StatusOr<v1::RenderResponse> moved = RenderAt(500'000, {MoveTo(1, 2.5)});
  const absl::StatusOr<v1::RenderResponse> copied = RenderAt(500'000, {MoveTo(1, 2.5, v1::ACTOR_EDIT_INSERT)});
  ASSERT_TRUE(plain.ok() && removed.ok() && moved.ok() && copied.ok())
      << removed.status() << moved.status() << copied.status();
  EXPECT_NE(plain->content_digest(), removed->content_digest());
  EXPECT_NE(plain->content_digest(), moved->content_digest());
  EXPECT_NE(moved->content_digest(), copied->content_digest());
  // The red block's pixels: there before, gone after the removal.
  const auto red = [](const v1::RenderResponse& r) {
    absl::StatusOr<client::DecodedImage> img = client::DecodeImage(r.frames(0).rgb());
    EXPECT_TRUE(img.ok());
    int n = 0;
    for (size_t p = 0; p + 2 < img->u8.size(); p += 3) n += img->u8[p] > 200 && img->u8[p + 1] < 80;
    return n;
  };
  EXPECT_GT(red(*plain), 50);
  EXPECT_LT(red(*removed), red(*plain) / 10);
  EXPECT_GT(red(*copied), red(*plain));
  // RenderTrajectory: every point with the edits.
  v1::RenderTrajectoryRequest traj;
  traj.set_scene("timed");
  traj.add_sensors()->set_sensor_id("cam_front");
  traj.add_points()->set_time_us(500'000);
  *traj.add_actor_edits() = Remove(1);
  std::vector<v1::TrajectoryFrame> frames;
  ASSERT_TRUE(client_->RenderTrajectory(traj, [&](const v1::TrajectoryFrame& f) {
    frames.push_back(f);
    return absl::OkStatus();
  }).ok());
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].response().content_digest(), removed->content_digest());
  // Unedited renders are as before the edits (nothing of an edit stays behind).
  EXPECT_EQ(RenderAt(500'000, {})->content_digest(), plain->content_digest());
}

// The LiDAR sees the same edited scene as the cameras: the block's returns go with it.
TEST_F(ActorsTest, TheLidarSeesTheEdits) {
  const auto sweep = [&](const std::vector<v1::ActorEdit>& edits) {
    v1::RenderRequest req;
    req.set_scene("timed");
    req.set_time_us(500'000);
    req.set_no_cameras(true);
    // The LiDAR at the block's height, 7 m behind it (the default rig mounts it on the ground).
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.translation() = Eigen::Vector3d(0, 0, 0.7);
    *req.mutable_t_world_from_sensor() = client::ToPose(T);
    req.mutable_lidar()->set_columns(512);
    for (const v1::ActorEdit& e : edits) *req.add_actor_edits() = e;
    absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
    EXPECT_TRUE(r.ok()) << r.status();
    absl::StatusOr<client::DecodedLidar> l = client::DecodeLidar(r->lidar());
    EXPECT_TRUE(l.ok()) << l.status();
    return l->range;
  };
  const std::vector<float> plain = sweep({}), removed = sweep({Remove(1)});
  ASSERT_EQ(plain.size(), removed.size());
  // Returns at the block (~7-9 m ahead) that end farther away, or none, once it is removed.
  int near_before = 0, changed = 0;
  for (size_t i = 0; i < plain.size(); ++i) {
    near_before += plain[i] > 5 && plain[i] < 10;
    changed += std::abs(plain[i] - removed[i]) > 0.5f;
  }
  EXPECT_GT(near_before, 20);
  EXPECT_GT(changed, 20);
}

TEST_F(ActorsTest, SessionsChangeTheirEditsAtAnyStep) {
  v1::CreateSessionRequest create;
  create.set_scene("timed");
  create.add_sensors()->set_sensor_id("cam_front");
  *create.add_actor_edits() = Remove(1);
  absl::StatusOr<v1::Session> session = client_->CreateSession(create);
  ASSERT_TRUE(session.ok()) << session.status();
  v1::StepRequest step;
  step.set_session_id(session->session_id());
  step.set_step_index(0);
  absl::StatusOr<v1::StepResponse> s0 = client_->Step(step);
  ASSERT_TRUE(s0.ok()) << s0.status();
  // As a Render at the step's time and ego pose with the same edits.
  const auto render_like = [&](const v1::StepResponse& r, const std::vector<v1::ActorEdit>& edits) {
    return RenderAt(r.time_us(), edits, "timed", &r.t_world_from_ego())->content_digest();
  };
  EXPECT_EQ(s0->content_digest(), render_like(*s0, {Remove(1)}));
  // Step 1 moves the actor instead; step 2 sets nothing and keeps the move; step 3 clears them.
  step.set_step_index(1);
  *step.mutable_actor_edits()->add_edits() = MoveTo(1, 2.5);
  absl::StatusOr<v1::StepResponse> s1 = client_->Step(step);
  ASSERT_TRUE(s1.ok()) << s1.status();
  EXPECT_EQ(s1->content_digest(), render_like(*s1, {MoveTo(1, 2.5)}));
  step.set_step_index(2);
  step.clear_actor_edits();
  absl::StatusOr<v1::StepResponse> s2 = client_->Step(step);
  ASSERT_TRUE(s2.ok());
  EXPECT_EQ(s2->content_digest(), render_like(*s2, {MoveTo(1, 2.5)}));
  step.set_step_index(3);
  step.mutable_actor_edits();  // set, empty: no edits from here
  absl::StatusOr<v1::StepResponse> s3 = client_->Step(step);
  ASSERT_TRUE(s3.ok());
  EXPECT_EQ(s3->content_digest(), render_like(*s3, {}));
  EXPECT_NE(s3->content_digest(), render_like(*s3, {Remove(1)}));
}

TEST_F(ActorsTest, BadEditsAreInvalidArgument) {
  v1::ActorEdit unknown = Remove(9);
  v1::ActorEdit unspecified = Remove(1);
  unspecified.set_kind(v1::ACTOR_EDIT_KIND_UNSPECIFIED);
  v1::ActorEdit nan = MoveTo(1, std::nan(""));
  v1::ActorEdit not_unit = MoveTo(1, 0);
  not_unit.mutable_trajectory(0)->mutable_t_world_from_actor()->mutable_rotation()->set_w(2);
  v1::ActorEdit backwards = MoveTo(1, 0);
  *backwards.add_trajectory() = backwards.trajectory(0);
  v1::ActorEdit removal_with_path = MoveTo(1, 0, v1::ACTOR_EDIT_REMOVE);
  for (const std::vector<v1::ActorEdit>& edits :
       std::vector<std::vector<v1::ActorEdit>>{{unknown}, {unspecified}, {nan}, {not_unit}, {backwards},
                                               {removal_with_path}, {Remove(1), Remove(1)},
                                               std::vector<v1::ActorEdit>(65, MoveTo(1, 0, v1::ACTOR_EDIT_INSERT))}) {
    const absl::StatusOr<v1::RenderResponse> r = RenderAt(0, edits);
    EXPECT_TRUE(absl::IsInvalidArgument(r.status())) << r.status();
  }
  // A scene without actors takes no edits.
  EXPECT_TRUE(absl::IsInvalidArgument(RenderAt(0, {Remove(1)}, "street").status()));
  // A session's bad edits: at its creation (shape) or its step (an actor the scene lacks).
  v1::CreateSessionRequest create;
  create.set_scene("timed");
  *create.add_actor_edits() = nan;
  EXPECT_TRUE(absl::IsInvalidArgument(client_->CreateSession(create).status()));
  create.clear_actor_edits();
  *create.add_actor_edits() = unknown;
  absl::StatusOr<v1::Session> session = client_->CreateSession(create);
  ASSERT_TRUE(session.ok());
  v1::StepRequest step;
  step.set_session_id(session->session_id());
  EXPECT_TRUE(absl::IsInvalidArgument(client_->Step(step).status()));
}

TEST_F(ActorsTest, AStaleActorSetIsRefusedByName) {
  // The scene trained again after its actors were extracted: another scene.ply.
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(data_root_ + "/timed/scene.ply");
  ASSERT_TRUE(store.ok());
  store->opacity_logits[0] += 1;
  ASSERT_TRUE(WriteGaussianPly(*store, data_root_ + "/timed/scene.ply").ok());
  const absl::StatusOr<v1::RenderResponse> r = RenderAt(0, {});
  EXPECT_FALSE(r.ok());
  EXPECT_NE(r.status().message().find("actors.json"), std::string::npos) << r.status();
}

}  // namespace
}  // namespace streetsim::testing
