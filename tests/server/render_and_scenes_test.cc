// ServerInfo, health, SceneService and RenderService against a real server.
#include <cmath>
#include <limits>

#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

class RenderTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    StartServer();
  }
  v1::RenderRequest SmallRequest() {
    v1::RenderRequest req;
    req.set_scene("timed");
    req.set_time_us(500000);
    auto* s = req.add_sensors();
    s->set_sensor_id("cam_front");
    req.mutable_outputs()->set_rgb(true);
    return req;
  }
};

TEST_F(RenderTest, ServerInfoAndHealth) {
  absl::StatusOr<v1::ServerInfo> info = client_->GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->api_version(), "1.0.0");
  EXPECT_EQ(info->backend(), "cpu");
  EXPECT_FALSE(info->device().empty());
  EXPECT_EQ(info->limits().max_image_width(), 4096);
  EXPECT_GT(info->limits().max_message_bytes(), 4 << 20);
  EXPECT_GT(info->load().server_rss_bytes(), 0);
  EXPECT_FALSE(info->auth_required());
  // Capabilities say what the server does now: LiDAR and fields yes; no placeholder left; this
  // test binary has no `streetsim` beside it, so jobs only initialise.
  const std::vector<std::string> caps(info->capabilities().begin(), info->capabilities().end());
  for (const char* c : {"render", "sessions", "lidar", "dynamic_scenes", "training:init-only"}) {
    EXPECT_NE(std::find(caps.begin(), caps.end(), c), caps.end()) << c;
  }
  for (const std::string& c : caps) EXPECT_EQ(c.find("placeholder"), std::string::npos) << c;
  absl::StatusOr<bool> serving = client_->IsServing();
  ASSERT_TRUE(serving.ok()) << serving.status();
  EXPECT_TRUE(*serving);
  serving = client_->IsServing("streetsim.v1.SessionService");
  ASSERT_TRUE(serving.ok());
  EXPECT_TRUE(*serving);
  EXPECT_EQ(client_->IsServing("no.such.Service").status().code(), absl::StatusCode::kNotFound);
}

TEST_F(RenderTest, ListGetLoadUnload) {
  absl::StatusOr<std::vector<v1::Scene>> scenes = client_->ListScenes();
  ASSERT_TRUE(scenes.ok()) << scenes.status();
  std::set<std::string> names;
  for (const v1::Scene& s : *scenes) names.insert(s.name());
  EXPECT_TRUE(names.count("street"));
  EXPECT_TRUE(names.count("timed"));
  EXPECT_TRUE(names.count("logs/fake/source"));  // bare .ply files anywhere up to depth 3
  absl::StatusOr<v1::Scene> timed = client_->GetScene("timed");
  ASSERT_TRUE(timed.ok()) << timed.status();
  EXPECT_TRUE(timed->has_time_range());
  EXPECT_EQ(timed->end_time_us(), 2000000);
  ASSERT_EQ(timed->rig().cameras_size(), 2);
  EXPECT_EQ(timed->rig().cameras(0).intrinsics().width(), 128);
  EXPECT_EQ(timed->ego_trajectory_size(), 2);
  EXPECT_EQ(timed->state(), v1::SCENE_STATE_AVAILABLE);

  absl::StatusOr<v1::Scene> street = client_->GetScene("street");
  ASSERT_TRUE(street.ok());
  EXPECT_FALSE(street->has_time_range());
  EXPECT_EQ(street->rig().cameras(0).intrinsics().width(), 1242);

  absl::StatusOr<v1::Scene> loading = client_->LoadScene("timed", /*wait=*/false);
  ASSERT_TRUE(loading.ok());
  EXPECT_TRUE(loading->state() == v1::SCENE_STATE_LOADING || loading->state() == v1::SCENE_STATE_READY);
  absl::StatusOr<v1::Scene> ready = client_->LoadScene("timed", /*wait=*/true);
  ASSERT_TRUE(ready.ok()) << ready.status();
  EXPECT_EQ(ready->state(), v1::SCENE_STATE_READY);
  EXPECT_EQ(ready->num_gaussians(), 4000u);
  EXPECT_TRUE(client_->UnloadScene("timed").ok());
  EXPECT_EQ(client_->GetScene("timed")->state(), v1::SCENE_STATE_AVAILABLE);

  for (const char* bad : {"nope", "../etc/passwd", "/etc/passwd", "timed/../street", ""}) {
    EXPECT_EQ(client_->GetScene(bad).status().code(), absl::StatusCode::kNotFound) << bad;
    EXPECT_EQ(client_->LoadScene(bad, true).status().code(), absl::StatusCode::kNotFound) << bad;
  }
}

TEST_F(RenderTest, SymlinkOutOfDataRootIsNotAScene) {
  const std::string outside = MakeTempDir("outside");
  ASSERT_TRUE(WriteGaussianPly(MakeSyntheticStreet({.num_gaussians = 10}), outside + "/x.ply").ok());
  fs::create_symlink(outside + "/x.ply", data_root_ + "/escape.ply");
  fs::create_directory_symlink(outside, data_root_ + "/escape_dir");
  EXPECT_EQ(client_->GetScene("escape").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client_->GetScene("escape_dir/x").status().code(), absl::StatusCode::kNotFound);
  fs::remove_all(outside);
}

TEST_F(RenderTest, RenderEncodingsDigestsAndTimings) {
  v1::RenderRequest req = SmallRequest();
  req.mutable_outputs()->set_depth(true);
  req.mutable_outputs()->set_alpha(true);
  absl::StatusOr<v1::RenderResponse> raw = client_->Render(req);
  ASSERT_TRUE(raw.ok()) << raw.status();
  ASSERT_EQ(raw->frames_size(), 1);
  const v1::SensorFrame& f = raw->frames(0);
  EXPECT_EQ(f.rgb().width(), 128);
  EXPECT_EQ(f.rgb().height(), 64);
  EXPECT_EQ(f.rgb().format(), v1::IMAGE_FORMAT_RGB8);
  EXPECT_EQ(f.rgb().data().size(), 128u * 64 * 3);
  EXPECT_EQ(f.depth().data().size(), 128u * 64 * 4);
  EXPECT_EQ(f.alpha().format(), v1::IMAGE_FORMAT_F32);
  EXPECT_GT(f.num_visible_gaussians(), 0u);
  EXPECT_GT(raw->timings().total_ms(), 0);
  EXPECT_EQ(raw->content_digest().rfind("fnv1a64w:", 0), 0u);
  absl::StatusOr<client::DecodedImage> depth = client::DecodeImage(f.depth());
  ASSERT_TRUE(depth.ok());
  float max_depth = 0;
  for (float d : depth->f32) max_depth = std::max(max_depth, d);
  EXPECT_GT(max_depth, 1.0f);

  // Deterministic: the same request gives the same bytes.
  absl::StatusOr<v1::RenderResponse> again = client_->Render(req);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->content_digest(), raw->content_digest());

  // PNG decodes to exactly the RAW pixels; JPEG is close; PNG16 depth within the scale.
  req.mutable_outputs()->set_rgb_encoding(v1::IMAGE_ENCODING_PNG);
  req.mutable_outputs()->set_depth_encoding(v1::DEPTH_ENCODING_PNG16);
  req.mutable_outputs()->set_alpha_encoding(v1::IMAGE_ENCODING_PNG);
  absl::StatusOr<v1::RenderResponse> png = client_->Render(req);
  ASSERT_TRUE(png.ok()) << png.status();
  absl::StatusOr<client::DecodedImage> rgb = client::DecodeImage(png->frames(0).rgb());
  ASSERT_TRUE(rgb.ok()) << rgb.status();
  EXPECT_EQ(rgb->u8, std::vector<uint8_t>(f.rgb().data().begin(), f.rgb().data().end()));
  EXPECT_DOUBLE_EQ(png->frames(0).depth().scale(), 1.0 / 256);
  absl::StatusOr<client::DecodedImage> d16 = client::DecodeImage(png->frames(0).depth());
  ASSERT_TRUE(d16.ok());
  for (size_t i = 0; i < d16->f32.size(); ++i) {
    ASSERT_NEAR(d16->f32[i], std::min(depth->f32[i], 65535.0f / 256), 0.5 / 256 + 1e-4) << i;
  }
  req.mutable_outputs()->set_rgb_encoding(v1::IMAGE_ENCODING_JPEG);
  req.mutable_outputs()->set_jpeg_quality(95);
  absl::StatusOr<v1::RenderResponse> jpg = client_->Render(req);
  ASSERT_TRUE(jpg.ok());
  EXPECT_EQ(jpg->frames(0).rgb().encoding(), v1::IMAGE_ENCODING_JPEG);
  EXPECT_TRUE(client::DecodeImage(jpg->frames(0).rgb()).ok());
}

TEST_F(RenderTest, PosesLogEgoSensorAndOverrides) {
  // No pose: the log trajectory at time_us; both rig cameras.
  v1::RenderRequest req;
  req.set_scene("timed");
  req.set_time_us(1000000);
  absl::StatusOr<v1::RenderResponse> log = client_->Render(req);
  ASSERT_TRUE(log.ok()) << log.status();
  ASSERT_EQ(log->frames_size(), 2);
  // Ego at x = 10 m (half-way), camera 1.5 m ahead of it.
  EXPECT_NEAR(log->frames(0).t_world_from_sensor().translation_m().x(), 11.5, 1e-9);
  // The same pose given explicitly renders the same bytes.
  Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
  ego.translation().x() = 10;
  *req.mutable_t_world_from_ego() = client::ToPose(ego);
  absl::StatusOr<v1::RenderResponse> explicit_pose = client_->Render(req);
  ASSERT_TRUE(explicit_pose.ok());
  EXPECT_EQ(explicit_pose->content_digest(), log->content_digest());
  // Sensor pose with a resolution override on a static scene.
  v1::RenderRequest s;
  s.set_scene("street");
  *s.mutable_t_world_from_sensor() = client::ToPose(StreetCameraPose(5.0));
  auto* sensor = s.add_sensors();
  sensor->set_sensor_id("cam_front");
  sensor->set_width(311);
  sensor->set_height(94);
  absl::StatusOr<v1::RenderResponse> r = client_->Render(s);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->frames(0).rgb().width(), 311);
  EXPECT_NEAR(r->frames(0).intrinsics().fx(), 721.5 * 311 / 1242, 1e-9);
  // A new sensor with explicit intrinsics and extrinsics.
  v1::RenderRequest n = SmallRequest();
  auto* extra = n.add_sensors();
  extra->set_sensor_id("cam_new");
  *extra->mutable_intrinsics() = log->frames(0).intrinsics();
  *extra->mutable_t_ego_from_sensor() = Identity();
  *n.mutable_t_world_from_ego() = Identity();
  absl::StatusOr<v1::RenderResponse> nr = client_->Render(n);
  ASSERT_TRUE(nr.ok()) << nr.status();
  EXPECT_EQ(nr->frames_size(), 2);
}

TEST_F(RenderTest, BadInputsGetCanonicalCodes) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  struct Case {
    const char* name;
    std::function<void(v1::RenderRequest*)> mutate;
    absl::StatusCode code;
  };
  const std::vector<Case> cases = {
      {"unknown scene", [](auto* r) { r->set_scene("nope"); }, absl::StatusCode::kNotFound},
      {"empty scene", [](auto* r) { r->set_scene(""); }, absl::StatusCode::kInvalidArgument},
      {"path scene", [](auto* r) { r->set_scene("../timed"); }, absl::StatusCode::kNotFound},
      {"time before", [](auto* r) { r->set_time_us(-1); }, absl::StatusCode::kOutOfRange},
      {"time after", [](auto* r) { r->set_time_us(2000001); }, absl::StatusCode::kOutOfRange},
      {"nan translation", [&](auto* r) { r->mutable_t_world_from_ego()->mutable_translation_m()->set_x(nan); r->mutable_t_world_from_ego()->mutable_rotation()->set_w(1); }, absl::StatusCode::kInvalidArgument},
      {"inf rotation", [&](auto* r) { r->mutable_t_world_from_ego()->mutable_rotation()->set_w(inf); }, absl::StatusCode::kInvalidArgument},
      {"non-unit rotation", [](auto* r) { r->mutable_t_world_from_ego()->mutable_rotation()->set_w(0.5); }, absl::StatusCode::kInvalidArgument},
      {"zero rotation", [](auto* r) { r->mutable_t_world_from_ego()->mutable_translation_m()->set_x(1); }, absl::StatusCode::kInvalidArgument},
      {"unknown sensor", [](auto* r) { r->mutable_sensors(0)->set_sensor_id("cam_nope"); }, absl::StatusCode::kNotFound},
      {"duplicate sensor", [](auto* r) { r->add_sensors()->set_sensor_id("cam_front"); }, absl::StatusCode::kInvalidArgument},
      {"empty sensor id", [](auto* r) { r->mutable_sensors(0)->set_sensor_id(""); }, absl::StatusCode::kInvalidArgument},
      {"resolution above limit", [](auto* r) { r->mutable_sensors(0)->set_width(5000); r->mutable_sensors(0)->set_height(100); }, absl::StatusCode::kInvalidArgument},
      {"negative resolution", [](auto* r) { r->mutable_sensors(0)->set_width(-5); r->mutable_sensors(0)->set_height(10); }, absl::StatusCode::kInvalidArgument},
      {"bad intrinsics", [](auto* r) { auto* k = r->mutable_sensors(0)->mutable_intrinsics(); k->set_width(10); k->set_height(10); k->set_fx(-1); k->set_fy(1); }, absl::StatusCode::kInvalidArgument},
      {"nan intrinsics", [&](auto* r) { auto* k = r->mutable_sensors(0)->mutable_intrinsics(); k->set_width(10); k->set_height(10); k->set_fx(1); k->set_fy(1); k->set_cx(nan); }, absl::StatusCode::kInvalidArgument},
      {"jpeg quality", [](auto* r) { r->mutable_outputs()->set_jpeg_quality(101); }, absl::StatusCode::kInvalidArgument},
      {"jpeg alpha", [](auto* r) { r->mutable_outputs()->set_alpha(true); r->mutable_outputs()->set_alpha_encoding(v1::IMAGE_ENCODING_JPEG); }, absl::StatusCode::kInvalidArgument},
      {"unknown encoding", [](auto* r) { r->mutable_outputs()->set_rgb_encoding(static_cast<v1::ImageEncoding>(42)); }, absl::StatusCode::kInvalidArgument},
      {"background", [](auto* r) { r->mutable_outputs()->mutable_background_rgb()->set_x(2); }, absl::StatusCode::kInvalidArgument},
      {"sensor pose with two sensors", [](auto* r) { *r->mutable_t_world_from_sensor() = Identity(); r->add_sensors()->set_sensor_id("cam_left"); }, absl::StatusCode::kInvalidArgument},
  };
  for (const Case& c : cases) {
    v1::RenderRequest req = SmallRequest();
    c.mutate(&req);
    absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
    EXPECT_EQ(r.status().code(), c.code) << c.name << ": " << r.status();
  }
  // Static scene without a trajectory needs a pose.
  v1::RenderRequest no_pose;
  no_pose.set_scene("street");
  EXPECT_EQ(client_->Render(no_pose).status().code(), absl::StatusCode::kInvalidArgument);
  // The server still works.
  EXPECT_TRUE(client_->Render(SmallRequest()).ok());
}

TEST_F(RenderTest, RenderTrajectoryStreamsInOrder) {
  v1::RenderTrajectoryRequest req;
  req.set_scene("timed");
  req.add_sensors()->set_sensor_id("cam_left");
  for (int i = 0; i < 4; ++i) req.add_points()->set_time_us(i * 400000);
  std::vector<int> indices;
  std::set<std::string> digests;
  absl::Status s = client_->RenderTrajectory(req, [&](const v1::TrajectoryFrame& f) {
    indices.push_back(f.index());
    digests.insert(f.response().content_digest());
    EXPECT_EQ(f.response().frames(0).rgb().width(), 96);
    return absl::OkStatus();
  });
  ASSERT_TRUE(s.ok()) << s;
  EXPECT_EQ(indices, (std::vector<int>{0, 1, 2, 3}));
  EXPECT_EQ(digests.size(), 4u);  // the ego moves: every frame differs
  // One bad point fails the whole request before anything renders.
  req.add_points()->set_time_us(9000000);
  int frames = 0;
  s = client_->RenderTrajectory(req, [&](const v1::TrajectoryFrame&) { ++frames; return absl::OkStatus(); });
  EXPECT_EQ(s.code(), absl::StatusCode::kOutOfRange);
  EXPECT_EQ(frames, 0);
  v1::RenderTrajectoryRequest empty;
  empty.set_scene("timed");
  EXPECT_EQ(client_->RenderTrajectory(empty, [](const auto&) { return absl::OkStatus(); }).code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(RenderLimitsTest, MessageSizeAndResolutionLimits) {
  const std::string data = MakeDataRoot();
  const std::string state = MakeTempDir("state");
  server::ServerOptions o = TestOptions(data, state);
  o.limits.max_message_bytes = 64 << 10;
  o.limits.max_image_width = 512;
  auto server = server::Server::Start(o);
  ASSERT_TRUE(server.ok()) << server.status();
  auto client = client::Client::Connect({.target = (*server)->address()});
  ASSERT_TRUE(client.ok());
  v1::RenderRequest req;
  req.set_scene("street");
  *req.mutable_t_world_from_sensor() = client::ToPose(StreetCameraPose(0));
  auto* s = req.add_sensors();
  s->set_sensor_id("cam_front");
  s->set_width(400);
  s->set_height(120);  // 144 kB of RGB8 > 64 kB
  EXPECT_EQ((*client)->Render(req).status().code(), absl::StatusCode::kResourceExhausted);
  s->set_width(600);
  EXPECT_EQ((*client)->Render(req).status().code(), absl::StatusCode::kInvalidArgument);
  server->reset();
  fs::remove_all(data);
  fs::remove_all(state);
}

}  // namespace
}  // namespace streetsim::testing
