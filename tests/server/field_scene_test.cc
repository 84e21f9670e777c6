// Dynamic scenes (DIR/field.bin beside scene.ply) served at the request's time: served renders
// equal local renders of the same deformation (field::ServingField) bit for bit, different times
// differ, times past the log clamp, a step's cameras and LiDAR share one field evaluation, and a
// bad field.bin fails the scene cleanly while the server keeps serving.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <random>
#include <tuple>

#include "render/engine.h"
#include "render/lidar/lidar_renderer.h"
#include "scene/field/field_io.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "scene/train/dynamic_stage.h"
#include "server/image_encoding.h"
#include "tests/server/moving_field.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

constexpr int64_t kLogEndUs = 2'000'000;  // the field's time range is [0, kLogEndUs]

Eigen::Isometry3d EgoFromLidar() {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.translation().z() = 1.73;
  return T;
}

class FieldSceneTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    SyntheticStreetOptions o;
    o.num_gaussians = 3000;
    o.sh_degree = 3;
    o.street_length_m = 60;
    store_ = MakeSyntheticStreet(o);
    field_ = std::make_unique<field::DeformationField>(MovingField(store_, 0, kLogEndUs));
    WriteScene("dyn", store_, *field_);
    StartServer();
  }

  // DIR/scene.ply + field.bin + scene.json without a time range (any request time is accepted;
  // the field clamps to its own range).
  void WriteScene(const std::string& name, const GaussianStore& g, const field::DeformationField& f) {
    const std::string dir = data_root_ + "/" + name;
    fs::create_directories(dir);
    ASSERT_TRUE(WriteGaussianPly(g, dir + "/scene.ply").ok());
    ASSERT_TRUE(field::SaveField(f, dir + "/" + field::kFieldFileName).ok());
    std::ofstream(dir + "/scene.json") << R"({"cameras": [
      {"sensor_id": "cam_front", "width": 128, "height": 64, "fx": 80, "fy": 80, "cx": 63.5, "cy": 31.5,
       "T_ego_from_cam": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}],
      "lidars": [{"sensor_id": "velodyne", "T_ego_from_lidar": [1,0,0,0, 0,1,0,0, 0,0,1,1.73, 0,0,0,1]}]})";
  }

  v1::RenderRequest At(int64_t time_us) const {
    v1::RenderRequest req;
    req.set_scene("dyn");
    req.set_time_us(time_us);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
    req.mutable_outputs()->set_rgb(true);
    req.mutable_outputs()->set_depth(true);
    return req;
  }

  std::string Digest(int64_t time_us) {
    absl::StatusOr<v1::RenderResponse> r = client_->Render(At(time_us));
    EXPECT_TRUE(r.ok()) << r.status();
    return r.ok() ? r->content_digest() : "";
  }

  int64_t Evaluations() {
    absl::StatusOr<v1::Scene> s = client_->GetScene("dyn");
    EXPECT_TRUE(s.ok()) << s.status();
    return s.ok() ? s->field_evaluations() : -1;
  }

  // The deformed store at time_us by the server's code path, here: the serving form fitted to the
  // exact field (the default), or with `exact` the field itself (--field-serving exact).
  GaussianStore LocalDeformed(int64_t time_us, bool exact = false) {
    ThreadPool pool(2);
    absl::StatusOr<field::ServingField> sf =
        field::ServingField::Create(*field_, store_, field::StaticSkipOptions{}, pool);
    EXPECT_TRUE(sf.ok()) << sf.status();
    if (!exact) {
      absl::StatusOr<std::unique_ptr<field::ServingForm>> form =
          field::ServingForm::Build(*sf, field::ServingFormOptions{}, pool);
      EXPECT_TRUE(form.ok()) << form.status();
      return **(*form)->At(time_us, pool);
    }
    absl::StatusOr<const GaussianStore*> g = sf->At(time_us, pool);
    EXPECT_TRUE(g.ok()) << g.status();
    return **g;
  }

  std::string LocalRgb(const GaussianStore& g) {
    absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
    EXPECT_TRUE(engine.ok());
    absl::StatusOr<std::unique_ptr<DeviceScene>> dev = (*engine)->Upload(g);
    EXPECT_TRUE(dev.ok()) << dev.status();
    RenderOptions opt;
    opt.want_alpha = false;
    RenderOutput out;
    EXPECT_TRUE((*engine)->Render(**dev, FrontCamera(8), opt, &out).ok());
    v1::Image rgb;
    EXPECT_TRUE(server::EncodeRgb(out.width, out.height, out.rgb, v1::IMAGE_ENCODING_RAW, 90, &rgb).ok());
    return rgb.data();
  }

  GaussianStore store_;
  std::unique_ptr<field::DeformationField> field_;
};

TEST_F(FieldSceneTest, ServedRenderEqualsLocalRenderOfTheDeformedScene) {
  absl::StatusOr<v1::Scene> loaded = client_->LoadScene("dyn", true);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  absl::StatusOr<v1::Scene> scene = client_->GetScene("dyn");
  ASSERT_TRUE(scene.ok());
  EXPECT_TRUE(scene->has_field());
  EXPECT_GT(scene->num_dynamic_gaussians(), 0u);
  EXPECT_GT(scene->load_time_s(), 0.0);
  EXPECT_EQ(scene->num_gaussians(), store_.size());

  const int64_t t = 700'000;
  absl::StatusOr<v1::RenderResponse> r = client_->Render(At(t));
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->frames_size(), 1);

  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(engine.ok());
  absl::StatusOr<std::unique_ptr<DeviceScene>> dev = (*engine)->Upload(LocalDeformed(t));
  ASSERT_TRUE(dev.ok()) << dev.status();
  const PinholeCamera cam = FrontCamera(8);  // cam_front of the scene.json below
  RenderOptions opt;
  opt.want_alpha = false;
  RenderOutput out;
  ASSERT_TRUE((*engine)->Render(**dev, cam, opt, &out).ok());
  v1::Image rgb, depth;
  ASSERT_TRUE(server::EncodeRgb(out.width, out.height, out.rgb, v1::IMAGE_ENCODING_RAW, 90, &rgb).ok());
  ASSERT_TRUE(server::EncodeDepth(out.width, out.height, out.depth, v1::DEPTH_ENCODING_F32, &depth).ok());
  EXPECT_GT(r->frames(0).num_visible_gaussians(), 50u);
  EXPECT_TRUE(r->frames(0).rgb().data() == rgb.data()) << "served RGB differs from the local render";
  EXPECT_TRUE(r->frames(0).depth().data() == depth.data()) << "served depth differs from the local render";

  // The trainer's full-field path (`streetsim render --scene DIR --time-us T`) is what the form
  // approximates: the images agree to within a few levels where the form's position error (mm here)
  // moves an edge by a fraction of a pixel.
  {
    ThreadPool pool(2);
    absl::StatusOr<GaussianStore> full = train::DeformedStore(*field_, store_, t, pool);
    ASSERT_TRUE(full.ok()) << full.status();
    absl::StatusOr<std::unique_ptr<DeviceScene>> full_dev = (*engine)->Upload(*full);
    ASSERT_TRUE(full_dev.ok());
    RenderOutput full_out;
    ASSERT_TRUE((*engine)->Render(**full_dev, cam, opt, &full_out).ok());
    v1::Image full_rgb;
    ASSERT_TRUE(server::EncodeRgb(full_out.width, full_out.height, full_out.rgb, v1::IMAGE_ENCODING_RAW, 90,
                                  &full_rgb).ok());
    ASSERT_EQ(full_rgb.data().size(), rgb.data().size());
    double sq = 0;
    for (size_t i = 0; i < rgb.data().size(); ++i) {
      sq += std::pow(int(uint8_t(rgb.data()[i])) - int(uint8_t(full_rgb.data()[i])), 2);
    }
    const double psnr = 10 * std::log10(255.0 * 255.0 / std::max(1e-9, sq / rgb.data().size()));
    EXPECT_GT(psnr, 40) << "served form against the exact field";
  }

  // The canonical scene renders differently: the field did move something in view.
  absl::StatusOr<std::unique_ptr<DeviceScene>> canon = (*engine)->Upload(store_);
  ASSERT_TRUE(canon.ok());
  RenderOutput canon_out;
  ASSERT_TRUE((*engine)->Render(**canon, cam, opt, &canon_out).ok());
  v1::Image canon_rgb;
  ASSERT_TRUE(server::EncodeRgb(canon_out.width, canon_out.height, canon_out.rgb, v1::IMAGE_ENCODING_RAW, 90,
                                &canon_rgb).ok());
  EXPECT_FALSE(canon_rgb.data() == rgb.data());
}

TEST_F(FieldSceneTest, DifferentTimesDifferAndTimesPastTheLogClamp) {
  const std::string early = Digest(300'000), late = Digest(1'700'000);
  EXPECT_NE(early, late);
  EXPECT_EQ(Digest(300'000), early);  // deterministic, also after another time
  const std::string start = Digest(0), end = Digest(kLogEndUs);
  EXPECT_NE(end, start);
  const int64_t before = Evaluations();
  EXPECT_EQ(Digest(kLogEndUs + 5'000'000), end);  // dynamic content holds its last state ...
  EXPECT_EQ(Digest(kLogEndUs + 1), end);
  EXPECT_EQ(Evaluations(), before);  // ... the same time coordinate: no new evaluation
  EXPECT_EQ(Digest(-1'000'000), start);  // and its first state before the log

  // RenderTrajectory: every point at its own time.
  v1::RenderTrajectoryRequest traj;
  traj.set_scene("dyn");
  traj.mutable_outputs()->set_rgb(true);
  traj.mutable_outputs()->set_depth(true);
  for (int64_t t : {int64_t{300'000}, int64_t{1'700'000}}) {
    v1::TrajectoryPoint* p = traj.add_points();
    p->set_time_us(t);
    *p->mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
  }
  std::vector<std::string> digests;
  absl::Status s = client_->RenderTrajectory(traj, [&](const v1::TrajectoryFrame& f) {
    digests.push_back(f.response().content_digest());
    return absl::OkStatus();
  });
  ASSERT_TRUE(s.ok()) << s;
  EXPECT_EQ(digests, (std::vector<std::string>{early, late}));
}

TEST_F(FieldSceneTest, CamerasAndLidarOfOneStepShareOneFieldEvaluation) {
  v1::CreateSessionRequest req;
  req.set_scene("dyn");
  req.set_start_time_us(200'000);  // not the load's time: step 0 evaluates
  req.set_step_dt_us(400'000);
  *req.mutable_initial_t_world_from_ego() = client::ToPose(EgoAt(8));
  req.mutable_lidar()->set_columns(256);
  req.mutable_lidar()->set_return_alpha_threshold(0.1);  // a sparse test scene
  absl::StatusOr<v1::Session> session = client_->CreateSession(req);
  ASSERT_TRUE(session.ok()) << session.status();
  ASSERT_TRUE(client_->LoadScene("dyn", true).ok());
  const int64_t e0 = Evaluations();
  std::vector<std::string> lidar_digests;
  for (int step = 0; step < 3; ++step) {
    v1::StepRequest s;
    s.set_session_id(session->session_id());
    s.set_step_index(step);
    absl::StatusOr<v1::StepResponse> r = client_->Step(s);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(r->frames_size(), 1);
    ASSERT_TRUE(r->has_lidar());
    EXPECT_EQ(Evaluations(), e0 + step + 1) << "step " << step;
    lidar_digests.push_back(r->lidar().digest());
    if (step == 1) {
      // The LiDAR saw the deformed scene of the step's time (t = 600 ms), as rendered here.
      LidarRenderer local;
      LidarRenderOptions opt;
      opt.sweep_start_us = 600'000;
      opt.return_alpha_threshold = 0.1f;
      LidarModel model = KittiHdl64e(256);
      model.T_ego_from_lidar = EgoFromLidar();
      LidarRenderOutput out;
      ASSERT_TRUE(local.Render(LocalDeformed(600'000), model, LidarSweepPose::Static(EgoAt(8) * EgoFromLidar()), opt,
                               &out).ok());
      size_t returns = 0, canonical_returns = 0;
      for (float v : out.range) returns += v > 0;
      LidarRenderOutput canon;
      ASSERT_TRUE(local.Render(store_, model, LidarSweepPose::Static(EgoAt(8) * EgoFromLidar()), opt, &canon).ok());
      for (float v : canon.range) canonical_returns += v > 0;
      EXPECT_GT(returns, 100u) << canonical_returns;
      ASSERT_EQ(r->lidar().range().size(), out.range.size() * 4);
      EXPECT_EQ(std::memcmp(r->lidar().range().data(), out.range.data(), r->lidar().range().size()), 0);
    }
    // An idempotent retry of the step costs nothing.
    ASSERT_TRUE(client_->Step(s).ok());
    EXPECT_EQ(Evaluations(), e0 + step + 1);
  }
  EXPECT_NE(lidar_digests[0], lidar_digests[2]);  // the LiDAR sees the motion too
}

TEST_F(FieldSceneTest, ABadFieldFailsItsSceneAndTheServerKeepsServing) {
  // A flipped byte in the parameters (checksum), a truncated file, and a valid field on a scene
  // whose Gaussians are not SH degree 3.
  const std::string good = data_root_ + "/dyn/" + field::kFieldFileName;
  for (const std::string name : {"flipped", "truncated"}) {
    WriteScene(name, store_, *field_);
    const std::string path = data_root_ + "/" + name + "/" + field::kFieldFileName;
    std::string bytes;
    {
      std::ifstream in(path, std::ios::binary);
      bytes.assign(std::istreambuf_iterator<char>(in), {});
    }
    if (name == "flipped") {
      bytes[bytes.size() / 2] ^= 0x40;
    } else {
      bytes.resize(bytes.size() - 100);
    }
    std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
  }
  SyntheticStreetOptions o;
  o.num_gaussians = 500;
  o.sh_degree = 1;
  WriteScene("degree1", MakeSyntheticStreet(o), *field_);
  for (const std::string name : {"flipped", "truncated", "degree1"}) {
    absl::StatusOr<v1::Scene> loaded = client_->LoadScene(name, true);
    ASSERT_FALSE(loaded.ok()) << name;
    EXPECT_EQ(loaded.status().code(), absl::StatusCode::kFailedPrecondition) << name;
    EXPECT_NE(loaded.status().message().find("field.bin"), absl::string_view::npos) << loaded.status();
    absl::StatusOr<v1::Scene> scene = client_->GetScene(name);
    ASSERT_TRUE(scene.ok());
    EXPECT_EQ(scene->state(), v1::SCENE_STATE_FAILED);
    EXPECT_NE(scene->error().find(name + "/field.bin"), std::string::npos) << scene->error();
    v1::RenderRequest req = At(0);
    req.set_scene(name);
    EXPECT_EQ(client_->Render(req).status().code(), absl::StatusCode::kFailedPrecondition) << name;
  }
  EXPECT_FALSE(Digest(500'000).empty());  // the good dynamic scene still serves
  v1::RenderRequest plain;
  plain.set_scene("street");
  *plain.mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
  EXPECT_TRUE(client_->Render(plain).ok());
  absl::StatusOr<v1::Scene> street = client_->GetScene("street");
  ASSERT_TRUE(street.ok());
  EXPECT_FALSE(street->has_field());  // a scene without field.bin: static, as before
  EXPECT_GT(street->load_time_s(), 0.0);
}

// `streetsim serve --static-motion-m / --static-sh` (ServerOptions::static_skip) reach the scenes:
// thresholds of 0 bake nothing and huge ones bake every Gaussian (this field moves every Gaussian
// by more than the default thresholds, so the default bakes nothing either).
TEST_F(FieldSceneTest, TheServersSkipThresholdsReachItsScenes) {
  absl::StatusOr<v1::Scene> by_default = client_->LoadScene("dyn", true);
  ASSERT_TRUE(by_default.ok()) << by_default.status();
  const uint64_t n = store_.size(), default_dynamic = by_default->num_dynamic_gaussians();
  EXPECT_GT(default_dynamic, 0u);
  for (const auto& [motion_m, sh, want] : {std::tuple<double, double, uint64_t>{0, 0, n}, {1e3, 1e3, 0}}) {
    client_.reset();
    server_.reset();
    server::ServerOptions o = TestOptions(data_root_, state_dir_);
    o.static_skip.motion_threshold_m = motion_m;
    o.static_skip.sh_threshold = sh;
    StartServer(o);
    absl::StatusOr<v1::Scene> loaded = client_->LoadScene("dyn", true);
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    EXPECT_EQ(loaded->num_dynamic_gaussians(), want) << motion_m;
    absl::StatusOr<v1::RenderResponse> r = client_->Render(At(700'000));
    EXPECT_TRUE(r.ok()) << r.status();
  }
}

// The serving form is built once and cached in DIR/field.serving; a restart reads it; a retrained
// field.bin makes it stale and the next load rebuilds it from the new field (never the old form);
// --field-serving exact serves the field's network, bit for bit as the exact serving path here.
TEST_F(FieldSceneTest, TheServingFormIsCachedRebuiltWhenStaleAndTheExactFieldSelectable) {
  const std::string dir = data_root_ + "/dyn";
  ASSERT_TRUE(client_->LoadScene("dyn", true).ok());
  ASSERT_TRUE(fs::exists(dir + "/field.serving"));
  const auto written = fs::last_write_time(dir + "/field.serving");
  const std::string first = Digest(700'000);
  client_.reset();
  server_.reset();
  StartServer();
  ASSERT_TRUE(client_->LoadScene("dyn", true).ok());
  EXPECT_EQ(fs::last_write_time(dir + "/field.serving"), written) << "a restart rebuilt a valid cache";
  EXPECT_EQ(Digest(700'000), first);

  // Retrained: another field in field.bin.
  *field_ = MovingField(store_, 0, kLogEndUs / 2);
  ASSERT_TRUE(field::SaveField(*field_, dir + "/" + field::kFieldFileName).ok());
  ASSERT_TRUE(client_->UnloadScene("dyn").ok());
  ASSERT_TRUE(client_->LoadScene("dyn", true).ok());
  absl::StatusOr<v1::RenderResponse> r = client_->Render(At(700'000));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->frames(0).rgb().data() == LocalRgb(LocalDeformed(700'000))) << "served a stale form";

  client_.reset();
  server_.reset();
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.exact_field = true;
  StartServer(o);
  r = client_->Render(At(700'000));
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->frames(0).rgb().data() == LocalRgb(LocalDeformed(700'000, true)));
  EXPECT_FALSE(r->frames(0).rgb().data() == LocalRgb(LocalDeformed(700'000)));
}

}  // namespace
}  // namespace streetsim::testing
