// A clip set served as one scene (docs/server.md "Clip sets"): a render, trajectory or session
// step at time t equals, byte for byte, the render of the clip that train::PickClip picks for t
// served alone (its Gaussians, field, LiDAR and learned background); between clips the nearer
// wins; a broken clip fails the set with its name; GetScene adds the clips' stats up; on a Vulkan
// engine the serving form's kernel writes the dynamic clip.
#include <fstream>
#include <random>

#include "scene/field/deformation_field.h"
#include "scene/field/field_io.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_stage.h"
#include "render/vulkan/vulkan_engine.h"
#include "tests/server/moving_field.h"
#include "tests/server/render_compare.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

// Clip k covers [kClipStartUs[k], kClipEndUs[k]]: 300 ms each, a 100 ms gap between them.
constexpr int64_t kClipStartUs[2] = {0, 400'000};
constexpr int64_t kClipEndUs[2] = {300'000, 700'000};
constexpr size_t kClipGaussians[2] = {1500, 2000};

class ClipSetServeTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    WriteSet("set", /*broken_field=*/false);
    WriteSet("broken", /*broken_field=*/true);
    StartServer();
  }

  // DATA_ROOT/NAME: clip_000 static (seed 1), clip_001 dynamic (seed 2, field.bin; garbage with
  // `broken_field`), each with scene.json (same rig, its time range and ego trajectory) and
  // train_meta.json (its own background), and clips.json.
  void WriteSet(const std::string& name, bool broken_field) {
    train::ClipSet set;
    set.clip_frames = 4;
    set.num_frames = 8;
    for (int k = 0; k < 2; ++k) {
      const std::string dir = data_root_ + "/" + name + "/" + train::ClipDirName(k);
      fs::create_directories(dir);
      SyntheticStreetOptions o;
      o.num_gaussians = kClipGaussians[k];
      o.sh_degree = 3;
      o.street_length_m = 60;
      o.seed = 1 + k;
      const GaussianStore g = MakeSyntheticStreet(o);
      ASSERT_TRUE(WriteGaussianPly(g, dir + "/scene.ply").ok());
      if (k == 1 && broken_field) {
        std::ofstream(dir + "/" + field::kFieldFileName) << "not a field";
      } else if (k == 1) {
        ASSERT_TRUE(field::SaveField(MovingField(g, kClipStartUs[k], kClipEndUs[k]),
                                     dir + "/" + field::kFieldFileName).ok());
      }
      const std::string t0 = std::to_string(kClipStartUs[k]), t1 = std::to_string(kClipEndUs[k]);
      std::ofstream(dir + "/scene.json") << R"({"time_range_us": [)" << t0 << ", " << t1 << R"(],
        "cameras": [
          {"sensor_id": "cam_front", "width": 128, "height": 64, "fx": 80, "fy": 80, "cx": 63.5, "cy": 31.5,
           "T_ego_from_cam": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}],
        "lidars": [{"sensor_id": "velodyne", "T_ego_from_lidar": [1,0,0,0, 0,1,0,0, 0,0,1,1.73, 0,0,0,1]}],
        "ego_trajectory": [
          {"time_us": )" << t0 << R"(, "T_world_from_ego": [1,0,0,)" << 10 * k
                                << R"(, 0,1,0,0, 0,0,1,0, 0,0,0,1]},
          {"time_us": )" << t1 << R"(, "T_world_from_ego": [1,0,0,)" << 10 * k + 3
                                << R"(, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]})";
      const char* background = k == 0 ? "[0.2, 0.4, 0.6]" : "[0.9, 0.1, 0.3]";
      std::ofstream(dir + "/train_meta.json") << R"({"background": )" << background
                                              << R"(, "resolution_scale": 1.0, "holdout_every": 4})";
      train::ClipEntry e;
      e.frames = {4 * k, 4 * k + 4};
      e.start_us = kClipStartUs[k];
      e.end_us = kClipEndUs[k];
      e.dir = train::ClipDirName(k);
      e.done = true;
      set.clips.push_back(e);
    }
    ASSERT_TRUE(train::WriteClipSet(set, data_root_ + "/" + name).ok());
  }

  // RGB + depth + a LiDAR sweep of `scene` at time_us from the ego pose x = x_m.
  v1::RenderResponse Render(const std::string& scene, int64_t time_us, double x_m) {
    v1::RenderRequest req;
    req.set_scene(scene);
    req.set_time_us(time_us);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(x_m));
    req.mutable_outputs()->set_rgb(true);
    req.mutable_outputs()->set_depth(true);
    req.mutable_lidar()->set_columns(256);
    req.mutable_lidar()->set_return_alpha_threshold(0.1);
    absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
    EXPECT_TRUE(r.ok()) << scene << " at " << time_us << ": " << r.status();
    return r.ok() ? *r : v1::RenderResponse();
  }

  static void ExpectSameImages(const v1::RenderResponse& a, const v1::RenderResponse& b, const std::string& what) {
    ASSERT_EQ(a.frames_size(), 1) << what;
    ASSERT_EQ(b.frames_size(), 1) << what;
    EXPECT_TRUE(a.frames(0).rgb().data() == b.frames(0).rgb().data()) << what << ": RGB differs";
    EXPECT_TRUE(a.frames(0).depth().data() == b.frames(0).depth().data()) << what << ": depth differs";
    EXPECT_TRUE(a.lidar().range() == b.lidar().range()) << what << ": LiDAR range differs";
    EXPECT_TRUE(a.lidar().intensity() == b.lidar().intensity()) << what << ": LiDAR intensity differs";
    EXPECT_EQ(a.content_digest(), b.content_digest()) << what;
  }

  // The RGB of pixel (0, 0).
  static Eigen::Vector3i CornerRgb(const v1::RenderResponse& r) {
    const std::string& d = r.frames(0).rgb().data();
    EXPECT_GE(d.size(), 3u);
    return d.size() < 3 ? Eigen::Vector3i(-1, -1, -1)
                        : Eigen::Vector3i(uint8_t(d[0]), uint8_t(d[1]), uint8_t(d[2]));
  }

  int64_t Evaluations(const std::string& scene) {
    absl::StatusOr<v1::Scene> s = client_->GetScene(scene);
    EXPECT_TRUE(s.ok()) << s.status();
    return s.ok() ? s->field_evaluations() : -1;
  }
};

TEST_F(ClipSetServeTest, RenderInEachClipEqualsTheClipServedAloneWithItsBackground) {
  absl::StatusOr<v1::Scene> scene = client_->GetScene("set");
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_TRUE(scene->error().empty()) << scene->error();
  EXPECT_TRUE(scene->has_time_range());
  EXPECT_EQ(scene->start_time_us(), 0);
  EXPECT_EQ(scene->end_time_us(), 700'000);
  EXPECT_EQ(scene->ego_trajectory_size(), 4);

  const v1::RenderResponse in0 = Render("set", 100'000, 5);
  const v1::RenderResponse in1 = Render("set", 500'000, 5);
  ExpectSameImages(in0, Render("set/clip_000", 100'000, 5), "clip 0");
  ExpectSameImages(in1, Render("set/clip_001", 500'000, 5), "clip 1");
  EXPECT_NE(in0.frames(0).rgb().data(), in1.frames(0).rgb().data()) << "both times rendered one clip";
  EXPECT_GT(in0.frames(0).num_visible_gaussians(), 50u);
  EXPECT_GT(in1.frames(0).num_visible_gaussians(), 50u);
  // Each clip's learned background (train_meta.json), within the 8-bit rounding: seen from 1 km
  // before the street, the corner pixel is sky.
  const Eigen::Vector3i sky0 = CornerRgb(Render("set", 100'000, -1000));
  const Eigen::Vector3i sky1 = CornerRgb(Render("set", 500'000, -1000));
  EXPECT_LE((sky0 - Eigen::Vector3i(51, 102, 153)).cwiseAbs().maxCoeff(), 1) << sky0.transpose();
  EXPECT_LE((sky1 - Eigen::Vector3i(230, 26, 77)).cwiseAbs().maxCoeff(), 1) << sky1.transpose();
  // A background in the request still wins.
  v1::RenderRequest req;
  req.set_scene("set");
  req.set_time_us(500'000);
  *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(-1000));
  req.mutable_outputs()->set_rgb(true);
  req.mutable_outputs()->mutable_background_rgb()->set_y(1.0);
  absl::StatusOr<v1::RenderResponse> green = client_->Render(req);
  ASSERT_TRUE(green.ok()) << green.status();
  EXPECT_EQ(CornerRgb(*green), Eigen::Vector3i(0, 255, 0));
}

TEST_F(ClipSetServeTest, BetweenClipsTheNearerClipRenders) {
  // 330 ms: 30 ms after clip 0, 70 ms before clip 1 (clip 0 is static: any time renders alike).
  ExpectSameImages(Render("set", 330'000, 5), Render("set/clip_000", 300'000, 5), "330 ms");
  // 380 ms: clip 1, whose field clamps to its own start.
  ExpectSameImages(Render("set", 380'000, 5), Render("set/clip_001", 400'000, 5), "380 ms");
  // 350 ms: a tie goes to the earlier clip.
  ExpectSameImages(Render("set", 350'000, 5), Render("set/clip_000", 0, 5), "350 ms");
  // Outside the union of the clips' ranges: out of range, as for a single scene.
  v1::RenderRequest req;
  req.set_scene("set");
  req.set_time_us(800'000);
  EXPECT_EQ(client_->Render(req).status().code(), absl::StatusCode::kOutOfRange);
}

TEST_F(ClipSetServeTest, SessionSteppingAcrossTheBoundarySwitchesClips) {
  v1::CreateSessionRequest create;
  create.set_scene("set");
  create.set_start_time_us(200'000);
  create.set_step_dt_us(100'000);
  create.mutable_outputs()->set_rgb(true);
  create.mutable_outputs()->set_depth(true);
  create.mutable_lidar()->set_columns(256);
  create.mutable_lidar()->set_return_alpha_threshold(0.1);
  absl::StatusOr<v1::Session> session = client_->CreateSession(create);
  ASSERT_TRUE(session.ok()) << session.status();
  // Steps at 200, 300 (clip 0), 400, 500 ms (clip 1).
  const char* clip_of_step[] = {"set/clip_000", "set/clip_000", "set/clip_001", "set/clip_001"};
  for (int i = 0; i < 4; ++i) {
    v1::StepRequest step;
    step.set_session_id(session->session_id());
    step.set_step_index(i);
    *step.mutable_t_world_from_ego() = client::ToPose(EgoAt(4 + i));
    absl::StatusOr<v1::StepResponse> r = client_->Step(step);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(r->time_us(), 200'000 + 100'000 * i);
    const v1::RenderResponse alone = Render(clip_of_step[i], r->time_us(), 4 + i);
    ASSERT_EQ(r->frames_size(), 1);
    EXPECT_TRUE(r->frames(0).rgb().data() == alone.frames(0).rgb().data()) << "step " << i;
    EXPECT_TRUE(r->frames(0).depth().data() == alone.frames(0).depth().data()) << "step " << i;
    EXPECT_TRUE(r->lidar().range() == alone.lidar().range()) << "step " << i;
    EXPECT_EQ(r->content_digest(), alone.content_digest()) << "step " << i;
  }
}

TEST_F(ClipSetServeTest, RenderTrajectoryPicksTheClipOfEachPoint) {
  v1::RenderTrajectoryRequest req;
  req.set_scene("set");
  req.mutable_outputs()->set_rgb(true);
  const int64_t times[] = {100'000, 600'000, 200'000};
  for (int64_t t : times) {
    v1::TrajectoryPoint* p = req.add_points();
    p->set_time_us(t);
    *p->mutable_t_world_from_ego() = client::ToPose(EgoAt(6));
  }
  std::vector<v1::TrajectoryFrame> frames;
  absl::Status s = client_->RenderTrajectory(req, [&](const v1::TrajectoryFrame& f) {
    frames.push_back(f);
    return absl::OkStatus();
  });
  ASSERT_TRUE(s.ok()) << s;
  ASSERT_EQ(frames.size(), 3u);
  for (int i = 0; i < 3; ++i) {
    v1::RenderRequest one;
    one.set_scene(times[i] < 350'000 ? "set/clip_000" : "set/clip_001");
    one.set_time_us(times[i]);
    *one.mutable_t_world_from_ego() = client::ToPose(EgoAt(6));
    one.mutable_outputs()->set_rgb(true);
    absl::StatusOr<v1::RenderResponse> alone = client_->Render(one);
    ASSERT_TRUE(alone.ok()) << alone.status();
    EXPECT_EQ(frames[i].response().content_digest(), alone->content_digest()) << "point " << i;
  }
}

TEST_F(ClipSetServeTest, GetSceneAddsTheClipsStatsUp) {
  ASSERT_TRUE(client_->LoadScene("set", true).ok());
  ASSERT_TRUE(client_->LoadScene("set/clip_001", true).ok());
  absl::StatusOr<v1::Scene> set = client_->GetScene("set");
  absl::StatusOr<v1::Scene> clip1 = client_->GetScene("set/clip_001");
  ASSERT_TRUE(set.ok() && clip1.ok());
  EXPECT_EQ(set->num_gaussians(), kClipGaussians[0] + kClipGaussians[1]);
  EXPECT_TRUE(set->has_field());
  EXPECT_GT(clip1->num_dynamic_gaussians(), 0u);
  EXPECT_EQ(set->num_dynamic_gaussians(), clip1->num_dynamic_gaussians());  // clip 0 is static
  const int64_t e0 = Evaluations("set");
  Render("set", 100'000, 5);  // clip 0: no field
  EXPECT_EQ(Evaluations("set"), e0);
  Render("set", 450'000, 5);
  Render("set", 550'000, 5);
  EXPECT_EQ(Evaluations("set"), e0 + 2);
  EXPECT_GE(set->load_time_s(), 0.0);
}

TEST_F(ClipSetServeTest, ABrokenClipFailsTheSetWithItsNameAndTheServerKeepsServing) {
  absl::StatusOr<v1::Scene> load = client_->LoadScene("broken", true);
  const std::string error = load.ok() ? load->error() : std::string(load.status().message());
  EXPECT_NE(error.find("clip_001"), std::string::npos) << error;
  EXPECT_NE(error.find(field::kFieldFileName), std::string::npos) << error;
  v1::RenderRequest req;
  req.set_scene("broken");
  req.set_time_us(100'000);  // even a time of the good clip: no half-served set
  absl::StatusOr<v1::RenderResponse> r = client_->Render(req);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition) << r.status();
  EXPECT_NE(r.status().message().find("clip_001"), std::string::npos) << r.status();
  // The broken set's good clip alone, and the healthy set, still render.
  Render("broken/clip_000", 100'000, 5);
  Render("set", 500'000, 5);
}

// On a Vulkan engine with --field-device vulkan, the dynamic clip's serving form is written into
// the engine's scene by the form's compute kernel (each clip is loaded as a scene, so each has its own
// writer; GetScene says "vulkan" for the set), and the set renders as it does with the same forms
// evaluated on the host and uploaded (--field-device cpu, the same engine), within float rounding
// (render_compare.h: the kernel may fuse multiply-adds), moving from one time to the next.
TEST_F(ClipSetServeTest, OnAVulkanEngineTheFormsKernelWritesTheDynamicClip) {
  if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device";
  auto start = [&](train::FieldDevice device, const std::string& state) {
    server::ServerOptions o = TestOptions(data_root_, state_dir_ + "/" + state);
    o.backend = Backend::kVulkan;
    o.field_device = device;
    return StartServerAndClient(o);
  };
  auto render = [](client::Client& c, int64_t time_us) {
    v1::RenderRequest req;
    req.set_scene("set");
    req.set_time_us(time_us);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(12));
    req.mutable_outputs()->set_rgb(true);
    req.mutable_outputs()->set_depth(true);
    absl::StatusOr<v1::RenderResponse> r = c.Render(req);
    EXPECT_TRUE(r.ok()) << time_us << ": " << r.status();
    EXPECT_TRUE(!r.ok() || r->frames_size() == 1) << time_us;
    return r.ok() && r->frames_size() == 1 ? r->frames(0) : v1::SensorFrame();
  };
  RunningServer kernel = start(train::FieldDevice::kVulkan, "kernel");
  RunningServer host = start(train::FieldDevice::kCpu, "host");
  ASSERT_TRUE(kernel.client && host.client);
  ASSERT_TRUE(kernel.client->LoadScene("set", true).ok());
  ASSERT_TRUE(host.client->LoadScene("set", true).ok());
  std::string previous;
  for (int64_t t : {450'000, 550'000, 100'000, 650'000}) {
    const v1::SensorFrame a = render(*kernel.client, t);
    const v1::SensorFrame b = render(*host.client, t);
    const std::string tag = "t=" + std::to_string(t);
    ExpectFramesWithinRounding(a, b, tag);
    if (t > kClipEndUs[0] && !previous.empty()) {
      EXPECT_GT(CompareRgb(previous, a.rgb().data()).max, 5) << tag << ": the clip did not move";
    }
    if (t > kClipEndUs[0]) previous = a.rgb().data();
  }
  absl::StatusOr<v1::Scene> k = kernel.client->GetScene("set");
  absl::StatusOr<v1::Scene> h = host.client->GetScene("set");
  ASSERT_TRUE(k.ok() && h.ok());
  EXPECT_EQ(k->field_device(), "vulkan") << "the kernel failed or was not used";
  EXPECT_EQ(h->field_device(), "cpu");
  EXPECT_EQ(k->field_serving(), "form");
}

}  // namespace
}  // namespace streetsim::testing
