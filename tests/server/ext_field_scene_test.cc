// Scenes trained with --field extended (DIR/field.bin + DIR/field_ext.bin) served at the request's
// time: a served render equals the local render of the same serving path bit for bit and the
// CLI's path (train::LoadSceneField + DeformedStore) within float rounding; different times
// differ; the static skip with the decoder's Δs agrees with the full evaluation within its
// thresholds; a damaged or another run's field_ext.bin fails its scene cleanly while the server
// keeps serving; a clip set serves each clip with its own extension.
#include <algorithm>
#include <cmath>
#include <fstream>
#include <random>

#include "render/engine.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/extended/extended_serving.h"
#include "scene/field/field_io.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_stage.h"
#include "server/image_encoding.h"
#include "tests/server/moving_extension.h"
#include "tests/server/moving_field.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

constexpr int64_t kLogEndUs = 2'000'000;  // the field's time range is [0, kLogEndUs]

constexpr char kRig[] = R"({"cameras": [
  {"sensor_id": "cam_front", "width": 128, "height": 64, "fx": 80, "fy": 80, "cx": 63.5, "cy": 31.5,
   "T_ego_from_cam": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}]})";

GaussianStore Street(uint64_t seed, size_t n) {
  SyntheticStreetOptions o;
  o.num_gaussians = n;
  o.sh_degree = 3;
  o.street_length_m = 60;
  o.seed = seed;
  return MakeSyntheticStreet(o);
}

// The served RAW RGB bytes of `g` rendered here by the cpu engine.
std::string LocalRgb(const GaussianStore& g, double x_m) {
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok());
  if (!engine.ok()) return "";
  absl::StatusOr<std::unique_ptr<DeviceScene>> dev = (*engine)->Upload(g);
  EXPECT_TRUE(dev.ok()) << dev.status();
  RenderOptions opt;
  opt.want_alpha = false;
  RenderOutput out;
  EXPECT_TRUE((*engine)->Render(**dev, FrontCamera(x_m), opt, &out).ok());
  v1::Image rgb;
  EXPECT_TRUE(server::EncodeRgb(out.width, out.height, out.rgb, v1::IMAGE_ENCODING_RAW, 90, &rgb).ok());
  return rgb.data();
}

int MaxByteDiff(const std::string& a, const std::string& b) {
  EXPECT_EQ(a.size(), b.size());
  int d = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) d = std::max(d, std::abs(int(uint8_t(a[i])) - int(uint8_t(b[i]))));
  return d;
}

// DIR/scene.ply + field.bin + field_ext.bin + scene.json.
void WriteExtendedScene(const std::string& dir, const GaussianStore& g, const field::ExtendedField& f,
                        const std::string& manifest = kRig) {
  fs::create_directories(dir);
  ASSERT_TRUE(WriteGaussianPly(g, dir + "/scene.ply").ok());
  ASSERT_TRUE(field::SaveField(f.base(), dir + "/" + field::kFieldFileName).ok());
  ASSERT_TRUE(field::SaveExtendedField(f, dir + "/" + field::kExtendedFieldFileName).ok());
  std::ofstream(dir + "/scene.json") << manifest;
}

class ExtFieldSceneTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    store_ = Street(1, 3000);
    ext_ = std::make_unique<field::ExtendedField>(MovingExtension(MovingField(store_, 0, kLogEndUs), 3));
    WriteExtendedScene(data_root_ + "/ext", store_, *ext_);
    // The exact field: these tests hold the served extended field against the exact serving path
    // and the CLI's; its serving form has a test of its own below.
    server::ServerOptions o = TestOptions(data_root_, state_dir_);
    o.exact_field = true;
    StartServer(o);
  }

  v1::RenderRequest At(const std::string& scene, int64_t time_us) const {
    v1::RenderRequest req;
    req.set_scene(scene);
    req.set_time_us(time_us);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
    req.mutable_outputs()->set_rgb(true);
    return req;
  }

  std::string ServedRgb(const std::string& scene, int64_t time_us) {
    absl::StatusOr<v1::RenderResponse> r = client_->Render(At(scene, time_us));
    EXPECT_TRUE(r.ok()) << r.status();
    return r.ok() && r->frames_size() == 1 ? r->frames(0).rgb().data() : "";
  }

  GaussianStore store_;
  std::unique_ptr<field::ExtendedField> ext_;
};

TEST_F(ExtFieldSceneTest, ServedRenderEqualsTheServingPathAndTheCliPath) {
  absl::StatusOr<v1::Scene> loaded = client_->LoadScene("ext", true);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE(loaded->has_field());
  EXPECT_EQ(loaded->num_gaussians(), store_.size());
  EXPECT_GT(loaded->num_dynamic_gaussians(), 0u);

  const int64_t t = 700'000;
  const std::string served = ServedRgb("ext", t);
  ASSERT_FALSE(served.empty());
  ThreadPool pool(0);
  // The serving path here (field::ExtServingField, the server's default static skip): bit for bit.
  {
    absl::StatusOr<std::unique_ptr<field::ExtServingField>> sf =
        field::ExtServingField::Create(*ext_, store_, field::StaticSkipOptions{}, pool);
    ASSERT_TRUE(sf.ok()) << sf.status();
    absl::StatusOr<const GaussianStore*> g = (*sf)->At(t, pool);
    ASSERT_TRUE(g.ok()) << g.status();
    EXPECT_TRUE(LocalRgb(**g, 8) == served) << "served RGB differs from the local serving path";
  }
  // The CLI's path (`streetsim render --scene DIR --time-us T`: LoadSceneField finds field_ext.bin,
  // DeformedStore runs the whole extended field): within float rounding (other row batches of
  // the GEMMs), at most 2 of 255 per channel.
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> cli = train::LoadSceneField(data_root_ + "/ext");
  ASSERT_TRUE(cli.ok()) << cli.status();
  ASSERT_TRUE(field::ExtensionOf(**cli)) << "the CLI did not load field_ext.bin";
  absl::StatusOr<GaussianStore> full = train::DeformedStore(**cli, store_, t, pool);
  ASSERT_TRUE(full.ok()) << full.status();
  EXPECT_LE(MaxByteDiff(LocalRgb(*full, 8), served), 2);
  // The extension matters: S3Gaussian's field alone (field.bin) renders another image.
  absl::StatusOr<GaussianStore> base_only = train::DeformedStore(ext_->base(), store_, t, pool);
  ASSERT_TRUE(base_only.ok());
  EXPECT_GT(MaxByteDiff(LocalRgb(*base_only, 8), served), 10);
}

// A form whose measured error is outside its bound is not served: the server says so and serves the
// exact field. Inside it, the form models the decoder's log-scale, rotation and opacity too, and
// renders as the form built here.
TEST_F(ExtFieldSceneTest, AFormOutsideItsBoundIsNotServedAndOneInsideServesTheDecoderHeads) {
  client_.reset();
  server_.reset();
  server::ServerOptions o = TestOptions(data_root_, state_dir_);
  o.serving_form.max_position_error_m = 1e-6;  // no form of this moving field is that close
  StartServer(o);
  absl::StatusOr<v1::Scene> loaded = client_->LoadScene("ext", true);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(loaded->field_serving(), "exact");
  EXPECT_EQ(loaded->field_form_error_m(), 0.0);

  client_.reset();
  server_.reset();
  o.serving_form.max_position_error_m = 1.0;
  StartServer(o);
  loaded = client_->LoadScene("ext", true);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(loaded->field_serving(), "form");
  EXPECT_GT(loaded->field_form_error_m(), 0.0);
  ThreadPool pool(0);
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> sf =
      field::ExtServingField::Create(*ext_, store_, field::StaticSkipOptions{}, pool);
  ASSERT_TRUE(sf.ok()) << sf.status();
  absl::StatusOr<std::unique_ptr<field::ServingForm>> form = field::ServingForm::Build(**sf, o.serving_form, pool);
  ASSERT_TRUE(form.ok()) << form.status();
  EXPECT_TRUE((*form)->models(field::FormGroup::kLogScale));
  EXPECT_TRUE((*form)->models(field::FormGroup::kRotation));
  EXPECT_TRUE((*form)->models(field::FormGroup::kOpacity));
  EXPECT_NEAR(loaded->field_form_error_m(), (*form)->error().max[0], 1e-7);
  const int64_t t = 700'000;
  EXPECT_TRUE(LocalRgb(**(*form)->At(t, pool), 8) == ServedRgb("ext", t));
}

TEST_F(ExtFieldSceneTest, DifferentTimesDifferAndOneTimeIsOneEvaluation) {
  const std::string early = ServedRgb("ext", 300'000), late = ServedRgb("ext", 1'700'000);
  ASSERT_FALSE(early.empty());
  EXPECT_NE(early, late);
  absl::StatusOr<v1::Scene> s0 = client_->GetScene("ext");
  ASSERT_TRUE(s0.ok());
  EXPECT_EQ(ServedRgb("ext", 1'700'000), late);
  EXPECT_EQ(ServedRgb("ext", 300'000), early);  // deterministic, also after another time
  EXPECT_EQ(ServedRgb("ext", kLogEndUs + 1), ServedRgb("ext", kLogEndUs + 5'000'000));  // held end state
  absl::StatusOr<v1::Scene> s1 = client_->GetScene("ext");
  ASSERT_TRUE(s1.ok());
  // 1.7 s again is the current time (free), 300 ms and the end cost one each, past the end is the end.
  EXPECT_EQ(s1->field_evaluations(), s0->field_evaluations() + 2);
}

// Gaussians uniformly in a 60 x 20 x 5 m box (no far outliers: the field's AABB is the box).
GaussianStore InBox(size_t n) {
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n);
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<float> u(0, 1), s(-0.3f, 0.3f);
  for (size_t i = 0; i < n; ++i) {
    g.means[i * 3] = 60 * u(rng);
    g.means[i * 3 + 1] = 20 * u(rng) - 10;
    g.means[i * 3 + 2] = 5 * u(rng);
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = -2 + s(rng);
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = (k == 0) + s(rng);
    g.opacity_logits[i] = 3 * s(rng);
    for (int k = 0; k < 48; ++k) g.sh[i * 48 + k] = s(rng);
  }
  return g;
}

// An extended field that moves half of `g`: every module but `temporal` (whose Fourier tokens
// vary with time for every Gaussian), on a base whose time planes vary only over the texel
// columns of the xt planes for one half of the AABB's x.
field::ExtendedField HalfMovingExtension(const GaussianStore& g) {
  field::DeformationField base = MovingField(g, 0, kLogEndUs);
  const field::FieldLayout& L = base.layout();
  std::vector<float>& p = base.mutable_params();
  for (const field::PlaneInfo& pi : L.planes) {
    if (!field::PlaneHasTime(pi.plane)) continue;
    for (int v = 0; v < pi.height; ++v) {
      for (int u = 0; u < pi.width; ++u) {
        if (pi.plane == 2 && u >= pi.width / 2) continue;  // xt, the moving half
        std::fill_n(p.begin() + pi.offset + (size_t(v) * pi.width + u) * L.channels, L.channels, 1.0f);
      }
    }
  }
  field::ExtendedFieldConfig c = field::ExtendedFieldConfig::AllOn();
  c.temporal = false;
  return MovingExtension(std::move(base), 4, c);
}

// The skip's error bound, channel by channel: static Gaussians within the thresholds of the full
// evaluation (at the analysis' sample times, where the bound is exact), dynamic ones and a
// disabled skip within float rounding.
TEST_F(ExtFieldSceneTest, StaticSkipOnAndOffAgreeWithinTheThresholds) {
  ThreadPool pool(0);
  const GaussianStore box = InBox(2000);
  const field::ExtendedField ext = HalfMovingExtension(box);
  field::StaticSkipOptions o;  // the server's thresholds
  o.num_samples = 11;  // sample s at s * 200 ms
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> skip = field::ExtServingField::Create(ext, box, o, pool);
  ASSERT_TRUE(skip.ok()) << skip.status();
  field::StaticSkipOptions off = o;
  off.enabled = false;
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> all = field::ExtServingField::Create(ext, box, off, pool);
  ASSERT_TRUE(all.ok()) << all.status();
  const size_t n = box.size(), nd = (*skip)->num_dynamic();
  EXPECT_GT(nd, n / 20) << "want both kinds";
  EXPECT_LT(nd, n - n / 20) << "want both kinds";
  EXPECT_EQ((*all)->num_dynamic(), n);

  double static_offset = 0;  // the largest time-independent Δx of a static Gaussian
  for (int64_t t : {int64_t{0}, int64_t{600'000}, int64_t{1'400'000}, kLogEndUs}) {
    absl::StatusOr<GaussianStore> full = field::ExtDeformedStore(ext, box, t, pool);
    ASSERT_TRUE(full.ok());
    absl::StatusOr<const GaussianStore*> s = (*skip)->At(t, pool);
    ASSERT_TRUE(s.ok());
    const GaussianStore& a = **s;
    const GaussianStore b = **(*all)->At(t, pool);
    // a: skip on (static Gaussians baked: within the thresholds), b: skip off (rounding).
    auto bound = [&](const std::vector<float>& x, const std::vector<float>& y, const std::vector<float>& z, int k,
                     double threshold, const char* what) {
      for (size_t i = 0; i < n; ++i) {
        for (int c = 0; c < k; ++c) {
          const float ref = z[i * k + c];
          ASSERT_NEAR(y[i * k + c], ref, 1e-4 * (1 + std::abs(ref))) << what << " skip off, Gaussian " << i;
          ASSERT_LE(std::abs(x[i * k + c] - ref), threshold + 1e-4 * (1 + std::abs(ref))) << what << " " << i;
        }
      }
    };
    bound(a.means, b.means, full->means, 3, o.motion_threshold_m, "mean");
    bound(a.sh, b.sh, full->sh, 48, o.sh_threshold, "SH");
    bound(a.log_scales, b.log_scales, full->log_scales, 3, o.log_scale_threshold, "log-scale");
    bound(a.rotations, b.rotations, full->rotations, 4, o.rotation_threshold, "rotation");
    bound(a.opacity_logits, b.opacity_logits, full->opacity_logits, 1, o.opacity_threshold, "opacity");
    for (size_t i = 0; i < n * 3; ++i) {
      if (a.means[i] != box.means[i] && std::abs(a.means[i] - full->means[i]) < 1e-6) {
        static_offset = std::max(static_offset, double(std::abs(full->means[i] - box.means[i])));
      }
    }
  }
  // The static Gaussians' Δs are baked, not dropped (a skip that left them canonical would fail above).
  EXPECT_GT(static_offset, 1e-2);
}

TEST_F(ExtFieldSceneTest, TheDecoderDeltasEnterTheStaticTest) {
  ThreadPool pool(0);
  field::StaticSkipOptions o;
  o.num_samples = 5;
  o.motion_threshold_m = o.sh_threshold = 1e9;  // Δx and ΔSH never make a Gaussian dynamic ...
  o.log_scale_threshold = o.rotation_threshold = o.opacity_threshold = 1e9;
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> loose = field::ExtServingField::Create(*ext_, store_, o, pool);
  ASSERT_TRUE(loose.ok());
  EXPECT_EQ((*loose)->num_dynamic(), 0u);
  for (double field::StaticSkipOptions::*th : {&field::StaticSkipOptions::log_scale_threshold,
                                              &field::StaticSkipOptions::rotation_threshold,
                                              &field::StaticSkipOptions::opacity_threshold}) {
    field::StaticSkipOptions one = o;
    one.*th = 1e-7;  // ... but this decoder head does
    absl::StatusOr<std::unique_ptr<field::ExtServingField>> sf = field::ExtServingField::Create(*ext_, store_, one, pool);
    ASSERT_TRUE(sf.ok());
    EXPECT_GT((*sf)->num_dynamic(), store_.size() * 9 / 10);
  }
}

TEST_F(ExtFieldSceneTest, ABadOrForeignFieldExtFailsItsSceneAndTheServerKeepsServing) {
  // A flipped byte, a truncated file, and a field_ext.bin of another run (its field.bin differs).
  const std::string good = data_root_ + "/ext/" + field::kExtendedFieldFileName;
  std::string bytes;
  {
    std::ifstream in(good, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), {});
  }
  for (const std::string name : {"flipped", "truncated"}) {
    WriteExtendedScene(data_root_ + "/" + name, store_, *ext_);
    std::string b = bytes;
    if (name == "flipped") {
      b[b.size() / 2] ^= 0x40;
    } else {
      b.resize(b.size() - 100);
    }
    std::ofstream(data_root_ + "/" + name + "/" + field::kExtendedFieldFileName, std::ios::binary | std::ios::trunc)
        << b;
  }
  {
    field::DeformationField other = ext_->base();
    other.mutable_params()[7] += 0.25f;  // another run's field.bin beside this run's field_ext.bin
    WriteExtendedScene(data_root_ + "/foreign", store_, *ext_);
    ASSERT_TRUE(field::SaveField(other, data_root_ + "/foreign/" + field::kFieldFileName).ok());
  }
  for (const std::string name : {"flipped", "truncated", "foreign"}) {
    absl::StatusOr<v1::Scene> loaded = client_->LoadScene(name, true);
    ASSERT_FALSE(loaded.ok()) << name;
    EXPECT_EQ(loaded.status().code(), absl::StatusCode::kFailedPrecondition) << name;
    absl::StatusOr<v1::Scene> scene = client_->GetScene(name);
    ASSERT_TRUE(scene.ok());
    EXPECT_EQ(scene->state(), v1::SCENE_STATE_FAILED);
    EXPECT_NE(scene->error().find(name + "/field_ext.bin"), std::string::npos) << scene->error();
    if (name == "foreign") {
      EXPECT_NE(scene->error().find("does not belong"), std::string::npos) << scene->error();
    }
    EXPECT_EQ(client_->Render(At(name, 0)).status().code(), absl::StatusCode::kFailedPrecondition) << name;
  }
  EXPECT_FALSE(ServedRgb("ext", 500'000).empty());  // the good extended scene still serves
  v1::RenderRequest plain;
  plain.set_scene("street");
  *plain.mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
  EXPECT_TRUE(client_->Render(plain).ok());
}

// A clip set (clips.json) whose clips each carry their own extension: a time in clip k renders
// what clip k alone renders, byte for byte, and what the CLI's path renders for clip k.
TEST_F(ExtFieldSceneTest, AClipSetServesEachClipWithItsOwnExtension) {
  constexpr int64_t kStartUs[2] = {0, 400'000}, kEndUs[2] = {300'000, 700'000};
  train::ClipSet set;
  set.clip_frames = 4;
  set.num_frames = 8;
  std::vector<GaussianStore> stores;
  for (int k = 0; k < 2; ++k) {
    const std::string dir = data_root_ + "/set/" + train::ClipDirName(k);
    stores.push_back(Street(5 + k, 1500));
    const std::string manifest = absl::StrCat(R"({"time_range_us": [)", kStartUs[k], ", ", kEndUs[k], "], ",
                                              std::string(kRig).substr(1));
    WriteExtendedScene(dir, stores[k], MovingExtension(MovingField(stores[k], kStartUs[k], kEndUs[k]), 7 + k),
                       manifest);
    train::ClipEntry e;
    e.frames = {4 * k, 4 * k + 4};
    e.start_us = kStartUs[k];
    e.end_us = kEndUs[k];
    e.dir = train::ClipDirName(k);
    e.done = true;
    set.clips.push_back(e);
  }
  ASSERT_TRUE(train::WriteClipSet(set, data_root_ + "/set").ok());
  ThreadPool pool(0);
  for (int k = 0; k < 2; ++k) {
    const int64_t t = kStartUs[k] + 100'000;
    const std::string in_set = ServedRgb("set", t);
    ASSERT_FALSE(in_set.empty()) << "clip " << k;
    EXPECT_TRUE(in_set == ServedRgb("set/" + train::ClipDirName(k), t)) << "clip " << k;
    const std::string dir = data_root_ + "/set/" + train::ClipDirName(k);
    absl::StatusOr<std::shared_ptr<const field::DeformationField>> cli = train::LoadSceneField(dir);
    ASSERT_TRUE(cli.ok()) << cli.status();
    absl::StatusOr<GaussianStore> full = train::DeformedStore(**cli, stores[k], t, pool);
    ASSERT_TRUE(full.ok()) << full.status();
    EXPECT_LE(MaxByteDiff(LocalRgb(*full, 8), in_set), 2) << "clip " << k;
    // The clip's extension was used: its field.bin alone renders another image.
    absl::StatusOr<field::DeformationField> base = field::LoadField(dir + "/" + field::kFieldFileName);
    ASSERT_TRUE(base.ok());
    absl::StatusOr<GaussianStore> base_only = train::DeformedStore(*base, stores[k], t, pool);
    ASSERT_TRUE(base_only.ok());
    EXPECT_GT(MaxByteDiff(LocalRgb(*base_only, 8), in_set), 10) << "clip " << k;
  }
}

}  // namespace
}  // namespace streetsim::testing
