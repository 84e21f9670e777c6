// LiDAR beside the cameras: Render and Step against a real server, compared with a local
// LidarRenderer render of the same scene bit for bit; bad LiDAR requests; the learned background
// of a trained scene (train_meta.json) in served camera renders.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>

#include <opencv2/imgcodecs.hpp>

#include "render/lidar/lidar_renderer.h"
#include "server/scene_manifest.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

// The LiDAR mounting written into lidarscene/scene.json.
Eigen::Isometry3d Mount() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation() = Eigen::Vector3d(0.8, 0.1, 1.73);
  T.linear() = Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  return T;
}

std::vector<float> Floats(const std::string& bytes) {
  std::vector<float> v(bytes.size() / 4);
  std::memcpy(v.data(), bytes.data(), v.size() * 4);
  return v;
}

// Number of floats that differ bitwise (and a short note), so a mismatch does not print 512 kB.
std::string Diff(const std::string& wire, const std::vector<float>& local) {
  if (wire.size() != local.size() * 4) return "size " + std::to_string(wire.size() / 4) + " vs " + std::to_string(local.size());
  const std::vector<float> w = Floats(wire);
  size_t differ = 0;
  double max_abs = 0;
  for (size_t i = 0; i < w.size(); ++i) {
    if (std::memcmp(&w[i], &local[i], 4) != 0) {
      ++differ;
      max_abs = std::max(max_abs, std::fabs(double(w[i]) - local[i]));
    }
  }
  return differ == 0 ? "" : std::to_string(differ) + " differ, max |d| " + std::to_string(max_abs);
}

class LidarServerTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    fs::create_directories(data_root_ + "/lidarscene");
    fs::copy_file(data_root_ + "/timed/scene.ply", data_root_ + "/lidarscene/scene.ply");
    const Eigen::Matrix4d m = Mount().matrix();
    std::string mount;
    char num[32];
    for (int i = 0; i < 16; ++i) {
      std::snprintf(num, sizeof num, "%.17g", m(i / 4, i % 4));  // exact round trip
      mount += (i ? "," : "") + std::string(num);
    }
    std::ofstream(data_root_ + "/lidarscene/scene.json") << R"({
      "cameras": [{"sensor_id": "cam_front", "width": 64, "height": 32, "fx": 40, "fy": 40, "cx": 31.5, "cy": 15.5,
                   "T_ego_from_cam": [0,0,1,0, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}],
      "lidars": [{"sensor_id": "velodyne", "T_ego_from_lidar": [)" + mount + R"(], "sweep_duration_us": 100000}],
      "ego_trajectory": [
        {"time_us": 0, "T_world_from_ego": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]},
        {"time_us": 2000000, "T_world_from_ego": [1,0,0,20, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]})";
    StartServer();
    absl::StatusOr<GaussianStore> store = ReadGaussianPly(data_root_ + "/lidarscene/scene.ply");
    ASSERT_TRUE(store.ok()) << store.status();
    store_ = std::move(*store);
  }

  // The same sweep rendered here, with the library the server uses.
  LidarRenderOutput Local(int columns, const LidarSweepPose& sweep, int64_t time_us, bool points) {
    LidarModel model = KittiHdl64e(columns);
    model.T_ego_from_lidar = Mount();
    LidarRenderOptions opt;
    opt.want_points = points;
    opt.sweep_start_us = time_us;
    LidarRenderOutput out;
    LidarRenderer renderer;
    EXPECT_TRUE(renderer.Render(store_, model, sweep, opt, &out).ok());
    return out;
  }

  GaussianStore store_;
};

Eigen::Isometry3d EgoAt(double x_m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation() = Eigen::Vector3d(x_m, 0.5, 0);
  return T;
}

TEST_F(LidarServerTest, RenderMatchesTheLocalRendererBitForBit) {
  v1::RenderRequest req;
  req.set_scene("lidarscene");
  req.set_time_us(500000);
  *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(12));
  req.mutable_lidar()->set_columns(512);
  req.mutable_lidar()->set_want_points(true);
  absl::StatusOr<v1::Scene> scene = client_->GetScene("lidarscene");
  ASSERT_TRUE(scene.ok()) << scene.status();
  ASSERT_EQ(scene->rig().lidars_size(), 1);
  EXPECT_EQ(scene->rig().lidars(0).sensor_id(), "velodyne");
  EXPECT_TRUE(client::FromPose(scene->rig().lidars(0).t_ego_from_sensor()).isApprox(Mount(), 1e-9));
  EXPECT_EQ(scene->rig().lidars(0).sweep_duration_us(), 100000);

  absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->frames_size(), 1);  // the camera too
  ASSERT_TRUE(r->has_lidar());
  const v1::LidarResult& l = r->lidar();
  EXPECT_EQ(l.sensor_id(), "velodyne");
  EXPECT_EQ(l.beams(), 64);
  EXPECT_EQ(l.columns(), 512);
  EXPECT_EQ(l.beam_elevation_deg_size(), 64);
  EXPECT_FALSE(l.rolling_sweep());  // an explicit ego pose is held for the sweep
  EXPECT_EQ(l.sweep_start_us(), 500000);
  EXPECT_TRUE(client::FromPose(l.t_ego_from_lidar()).isApprox(Mount(), 1e-9));
  EXPECT_TRUE(client::FromPose(l.t_world_from_lidar()).isApprox(EgoAt(12) * Mount(), 1e-9));
  ASSERT_EQ(l.range().size(), 64u * 512 * 4);

  const LidarRenderOutput local = Local(512, LidarSweepPose::Static(EgoAt(12) * Mount()), 500000, true);
  EXPECT_EQ(Diff(l.range(), local.range), "");
  EXPECT_EQ(Diff(l.intensity(), local.intensity), "");
  EXPECT_EQ(Diff(l.alpha(), local.alpha), "");
  size_t returns = 0;
  for (float v : Floats(l.range())) returns += v > 0;
  EXPECT_GT(returns, 200u);
  ASSERT_EQ(l.points().count(), local.points.size());
  EXPECT_EQ(l.points().count(), returns);
  EXPECT_EQ(l.points().xyz().size(), returns * 12);
  EXPECT_EQ(l.points().time_us().size(), returns * 8);
  EXPECT_EQ(l.digest().rfind("fnv1a64w:", 0), 0u);
  EXPECT_GT(l.timings().total_ms(), 0);

  // Deterministic, and the LiDAR is part of the response digest.
  absl::StatusOr<v1::RenderResponse> again = client_->Render(req);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->content_digest(), r->content_digest());
  req.clear_lidar();
  absl::StatusOr<v1::RenderResponse> no_lidar = client_->Render(req);
  ASSERT_TRUE(no_lidar.ok());
  EXPECT_FALSE(no_lidar->has_lidar());
  EXPECT_NE(no_lidar->content_digest(), r->content_digest());
}

TEST_F(LidarServerTest, LogPoseGivesARollingSweepAndNoCamerasRendersOnlyTheLidar) {
  v1::RenderRequest req;
  req.set_scene("lidarscene");
  req.set_time_us(1000000);  // the log's ego at x = 10 m, moving 10 m/s
  req.set_no_cameras(true);
  req.mutable_lidar()->set_columns(256);
  absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->frames_size(), 0);
  const v1::LidarResult& l = r->lidar();
  EXPECT_TRUE(l.rolling_sweep());
  const Eigen::Isometry3d start = client::FromPose(l.t_world_from_lidar());
  const Eigen::Isometry3d end = client::FromPose(l.t_world_from_lidar_end());
  EXPECT_NEAR((end.translation() - start.translation()).x(), 1.0, 1e-9);  // 100 ms at 10 m/s
  server::SceneManifest m;
  m.ego_trajectory = {{0, Eigen::Isometry3d::Identity()}, {2000000, Eigen::Isometry3d::Identity()}};
  m.ego_trajectory[1].T_world_from_ego.translation().x() = 20;
  const LidarSweepPose sweep{*m.EgoPoseAt(1000000) * Mount(), *m.EgoPoseAt(1100000) * Mount()};
  EXPECT_EQ(Diff(l.range(), Local(256, sweep, 1000000, false).range), "");

  // T_world_from_sensor with no cameras: the LiDAR's own pose, held.
  *req.mutable_t_world_from_sensor() = client::ToPose(EgoAt(5));
  r = client_->Render(req);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->lidar().rolling_sweep());
  EXPECT_EQ(Diff(r->lidar().range(), Local(256, LidarSweepPose::Static(EgoAt(5)), 1000000, false).range), "");
}

TEST_F(LidarServerTest, TrajectoryPointsCarryTheirOwnSweeps) {
  v1::RenderTrajectoryRequest traj;
  traj.set_scene("lidarscene");
  traj.mutable_lidar()->set_columns(256);
  v1::TrajectoryPoint* p0 = traj.add_points();  // explicit ego pose: a held sweep
  p0->set_time_us(500000);
  *p0->mutable_t_world_from_ego() = client::ToPose(EgoAt(12));
  traj.add_points()->set_time_us(1000000);  // the log's pose: a rolling sweep
  std::vector<v1::TrajectoryFrame> frames;
  absl::Status s = client_->RenderTrajectory(traj, [&](const v1::TrajectoryFrame& f) {
    frames.push_back(f);
    return absl::OkStatus();
  });
  ASSERT_TRUE(s.ok()) << s;
  ASSERT_EQ(frames.size(), 2u);
  for (const v1::TrajectoryFrame& f : frames) {
    ASSERT_TRUE(f.response().has_lidar()) << f.index();
    EXPECT_EQ(f.response().frames_size(), 1);  // the camera too
  }
  EXPECT_FALSE(frames[0].response().lidar().rolling_sweep());
  EXPECT_EQ(Diff(frames[0].response().lidar().range(),
                 Local(256, LidarSweepPose::Static(EgoAt(12) * Mount()), 500000, false).range),
            "");
  EXPECT_TRUE(frames[1].response().lidar().rolling_sweep());
  // The same as a single Render of each point.
  v1::RenderRequest single;
  single.set_scene("lidarscene");
  single.set_time_us(1000000);
  single.mutable_lidar()->set_columns(256);
  absl::StatusOr<v1::RenderResponse> r = client_->Render(single);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(r->content_digest(), frames[1].response().content_digest());

  // A sensor pose cannot place a LiDAR beside the cameras: refused before anything renders.
  *traj.add_points()->mutable_t_world_from_sensor() = client::ToPose(EgoAt(5));
  traj.mutable_points(2)->set_time_us(700000);
  traj.mutable_sensors()->Add()->set_sensor_id("cam_front");
  frames.clear();
  s = client_->RenderTrajectory(traj, [&](const v1::TrajectoryFrame& f) {
    frames.push_back(f);
    return absl::OkStatus();
  });
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << s;
  EXPECT_NE(std::string(s.message()).find("points[2]"), std::string::npos) << s;
  EXPECT_TRUE(frames.empty());
  // A bad LiDAR request is refused as in Render.
  traj.mutable_points()->RemoveLast();
  traj.mutable_lidar()->set_columns(-1);
  EXPECT_EQ(client_->RenderTrajectory(traj, [](const v1::TrajectoryFrame&) { return absl::OkStatus(); }).code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(LidarServerTest, BadLidarRequestsAreInvalidArgument) {
  auto base = [] {
    v1::RenderRequest req;
    req.set_scene("lidarscene");
    req.set_time_us(0);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(0));
    req.mutable_lidar()->set_columns(128);
    return req;
  };
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<std::pair<std::string, v1::RenderRequest>> bad;
  auto add = [&](const std::string& what, auto edit) {
    v1::RenderRequest r = base();
    edit(r);
    bad.emplace_back(what, r);
  };
  add("columns -1", [](v1::RenderRequest& r) { r.mutable_lidar()->set_columns(-1); });
  add("columns 65537", [](v1::RenderRequest& r) { r.mutable_lidar()->set_columns(65537); });
  add("columns 2^31-1", [](v1::RenderRequest& r) { r.mutable_lidar()->set_columns(std::numeric_limits<int>::max()); });
  add("min NaN", [&](v1::RenderRequest& r) { r.mutable_lidar()->set_min_range_m(nan); });
  add("max inf", [](v1::RenderRequest& r) { r.mutable_lidar()->set_max_range_m(INFINITY); });
  add("min negative", [](v1::RenderRequest& r) { r.mutable_lidar()->set_min_range_m(-1); });
  add("min >= max", [](v1::RenderRequest& r) {
    r.mutable_lidar()->set_min_range_m(50);
    r.mutable_lidar()->set_max_range_m(40);
  });
  add("threshold 2", [](v1::RenderRequest& r) { r.mutable_lidar()->set_return_alpha_threshold(2); });
  add("threshold NaN", [&](v1::RenderRequest& r) { r.mutable_lidar()->set_return_alpha_threshold(nan); });
  add("points frame 99", [](v1::RenderRequest& r) {
    r.mutable_lidar()->set_points_frame(static_cast<v1::LidarPointFrame>(99));
  });
  add("mounting NaN", [&](v1::RenderRequest& r) {
    v1::Pose p = client::ToPose(Eigen::Isometry3d::Identity());
    p.mutable_translation_m()->set_x(nan);
    *r.mutable_lidar()->mutable_t_ego_from_lidar() = p;
  });
  add("no_cameras without lidar", [](v1::RenderRequest& r) {
    r.clear_lidar();
    r.set_no_cameras(true);
  });
  add("sensor pose with cameras", [](v1::RenderRequest& r) {
    *r.mutable_t_world_from_sensor() = client::ToPose(Eigen::Isometry3d::Identity());
    r.add_sensors()->set_sensor_id("cam_front");
  });
  for (const auto& [what, req] : bad) {
    absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << what << ": " << r.status();
  }
  // A server-side error never leaves the server unable to serve.
  EXPECT_TRUE(client_->Render(base()).ok());

  v1::CreateSessionRequest create;
  create.set_scene("lidarscene");
  create.mutable_lidar()->set_columns(70000);
  EXPECT_EQ(client_->CreateSession(create).status().code(), absl::StatusCode::kInvalidArgument);
}

TEST_F(LidarServerTest, SessionStepsReturnTheLidar) {
  v1::CreateSessionRequest create;
  create.set_scene("lidarscene");
  create.mutable_lidar()->set_columns(256);
  create.mutable_lidar()->set_want_points(true);
  create.mutable_lidar()->set_points_frame(v1::LIDAR_POINT_FRAME_EGO);
  absl::StatusOr<v1::Session> s = client_->CreateSession(create);
  ASSERT_TRUE(s.ok()) << s.status();

  // Step 0: teleport; the sweep is held at that pose.
  v1::StepRequest step;
  step.set_session_id(s->session_id());
  step.set_step_index(0);
  *step.mutable_t_world_from_ego() = client::ToPose(EgoAt(12));
  absl::StatusOr<v1::StepResponse> r = client_->Step(step);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(r->has_lidar());
  EXPECT_EQ(r->frames_size(), 1);
  EXPECT_FALSE(r->lidar().rolling_sweep());
  EXPECT_EQ(r->lidar().points().frame(), v1::LIDAR_POINT_FRAME_EGO);
  EXPECT_EQ(Diff(r->lidar().range(), Local(256, LidarSweepPose::Static(EgoAt(12) * Mount()), 0, false).range), "");
  EXPECT_GT(r->lidar().points().count(), 0u);

  // Step 1 (t = 100 ms) follows a trajectory: the sweep rolls from its pose at 100 ms to 200 ms.
  step.set_step_index(1);
  v1::EgoTrajectory* traj = step.mutable_trajectory();
  for (int k = 0; k <= 3; ++k) {
    v1::TimedPose* p = traj->add_poses();
    p->set_time_us(k * 100000);
    *p->mutable_t_world_from_ego() = client::ToPose(EgoAt(12 + 2.0 * k));
  }
  step.mutable_lidar()->set_columns(128);  // this step's own LiDAR request
  r = client_->Step(step);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->lidar().rolling_sweep());
  EXPECT_EQ(r->lidar().columns(), 128);
  EXPECT_FALSE(r->lidar().has_points());  // the step's request replaces the session's
  const LidarSweepPose sweep{EgoAt(14) * Mount(), EgoAt(16) * Mount()};
  EXPECT_EQ(Diff(r->lidar().range(), Local(128, sweep, 100000, false).range), "");

  // A bad LiDAR request fails the step and leaves the session where it was.
  v1::StepRequest bad;
  bad.set_session_id(s->session_id());
  bad.set_step_index(2);
  bad.mutable_lidar()->set_min_range_m(std::numeric_limits<double>::quiet_NaN());
  EXPECT_EQ(client_->Step(bad).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(client_->GetSession(s->session_id())->last_step_index(), 1);
}

TEST_F(LidarServerTest, CliRendersTheLidarFromTheServer) {
  const std::string out = data_root_ + "/range.tiff";
  const std::string log = data_root_ + "/cli.log";
  const std::string cli = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim render --server " + server_->address() +
                          " --scene lidarscene --lidar --time-us 500000 --out-range " + out;
  int status = std::system((cli + " --columns 256 >" + log + " 2>&1").c_str());
  ASSERT_EQ(WEXITSTATUS(status), 0) << std::ifstream(log).rdbuf();
  const cv::Mat range = cv::imread(out, cv::IMREAD_UNCHANGED);
  ASSERT_EQ(range.type(), CV_32FC1);
  ASSERT_EQ(range.rows, 64);
  ASSERT_EQ(range.cols, 256);
  server::SceneManifest m;
  m.ego_trajectory = {{0, Eigen::Isometry3d::Identity()}, {2000000, Eigen::Isometry3d::Identity()}};
  m.ego_trajectory[1].T_world_from_ego.translation().x() = 20;
  const LidarSweepPose sweep{*m.EgoPoseAt(500000) * Mount(), *m.EgoPoseAt(600000) * Mount()};
  const std::vector<float> local = Local(256, sweep, 500000, false).range;
  EXPECT_EQ(Diff(std::string(reinterpret_cast<const char*>(range.ptr<float>()), range.total() * 4), local), "");
  status = std::system((cli + " --columns 70000 >" + log + " 2>&1").c_str());
  EXPECT_EQ(WEXITSTATUS(status), 2);
}

TEST_F(LidarServerTest, TrainedSceneBackgroundIsUsedInCameraRenders) {
  // A scene whose Gaussians are all behind the camera: every pixel is background.
  fs::create_directories(data_root_ + "/trained");
  GaussianStore one;
  one.Resize(1);
  one.means = {-50, 0, 0};
  one.log_scales = {0, 0, 0};
  one.rotations = {1, 0, 0, 0};
  one.opacity_logits = {2};
  ASSERT_TRUE(WriteGaussianPly(one, data_root_ + "/trained/scene.ply").ok());
  std::ofstream(data_root_ + "/trained/train_meta.json")
      << R"({"background": [0.2, 0.4, 0.6], "resolution_scale": 0.5, "holdout_every": 4})";
  fs::create_directories(data_root_ + "/untrained");
  ASSERT_TRUE(WriteGaussianPly(one, data_root_ + "/untrained/scene.ply").ok());

  v1::RenderRequest req;
  req.set_scene("trained");
  req.set_time_us(0);
  *req.mutable_t_world_from_ego() = client::ToPose(Eigen::Isometry3d::Identity());
  v1::SensorRequest* sensor = req.add_sensors();
  sensor->set_sensor_id("cam_front");
  sensor->set_width(32);
  sensor->set_height(16);
  absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
  ASSERT_TRUE(r.ok()) << r.status();
  const std::string& rgb = r->frames(0).rgb().data();
  ASSERT_EQ(rgb.size(), 32u * 16 * 3);
  EXPECT_EQ(static_cast<uint8_t>(rgb[0]), 51);
  EXPECT_EQ(static_cast<uint8_t>(rgb[1]), 102);
  EXPECT_EQ(static_cast<uint8_t>(rgb[2]), 153);

  // The request's own background wins; a scene without train_meta.json stays black.
  req.mutable_outputs()->mutable_background_rgb()->set_x(1);
  r = client_->Render(req);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(static_cast<uint8_t>(r->frames(0).rgb().data()[0]), 255);
  EXPECT_EQ(static_cast<uint8_t>(r->frames(0).rgb().data()[1]), 0);
  req.clear_outputs();
  req.set_scene("untrained");
  r = client_->Render(req);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(static_cast<uint8_t>(r->frames(0).rgb().data()[2]), 0);

  // Sessions use it too.
  v1::CreateSessionRequest create;
  create.set_scene("trained");
  *create.add_sensors() = *sensor;
  absl::StatusOr<v1::Session> s = client_->CreateSession(create);
  ASSERT_TRUE(s.ok()) << s.status();
  v1::StepRequest step;
  step.set_session_id(s->session_id());
  step.set_step_index(0);
  absl::StatusOr<v1::StepResponse> st = client_->Step(step);
  ASSERT_TRUE(st.ok()) << st.status();
  EXPECT_EQ(static_cast<uint8_t>(st->frames(0).rgb().data()[1]), 102);

  // A malformed train_meta.json makes the scene unusable with a clear error, not a black sky.
  fs::create_directories(data_root_ + "/broken");
  ASSERT_TRUE(WriteGaussianPly(one, data_root_ + "/broken/scene.ply").ok());
  std::ofstream(data_root_ + "/broken/train_meta.json") << "{not json";
  req.set_scene("broken");
  absl::StatusOr<v1::RenderResponse> broken = client_->Render(req);
  EXPECT_FALSE(broken.ok());
  EXPECT_NE(broken.status().message().find("train_meta.json"), std::string::npos) << broken.status();
}

}  // namespace
}  // namespace streetsim::testing
