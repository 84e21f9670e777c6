// The served field on a Vulkan device (serve --field-device, docs/server.md "Field device"): with
// the device forced to Vulkan (lavapipe here) the deformed scenes and the served renders equal the
// cpu's within float rounding, for S3Gaussian's field and the extended one, with and without the
// static skip; a device that fails at creation or mid-serving leaves the scene on the cpu with
// the cpu's exact results and no failed request; bad --field-device values exit 2.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>

#include "render/params_view.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/extended/extended_serving.h"
#include "scene/field/field_eval.h"
#include "scene/field/field_io.h"
#include "scene/field/host_planes_writer.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "render/vulkan/field/vulkan_serving.h"
#include "tests/common/cli_runner.h"
#include "tests/common/scratch_dir.h"
#include "tests/server/moving_extension.h"
#include "tests/server/moving_field.h"
#include "tests/server/render_compare.h"
#include "server/dynamic_scene_field.h"
#include "tests/server/server_fixture.h"

namespace streetsim::testing {
namespace {

constexpr int64_t kLogEndUs = 2'000'000;  // the fields' time range is [0, kLogEndUs]
const int64_t kTimesUs[] = {0, 700'000, 1'300'000, kLogEndUs};

// The bound on |vulkan - cpu| / (1 + |cpu|) of every deformed parameter. Both sides evaluate the
// same float formulas; the device sums the MLP's dot products (tiled GEMMs) and the plane
// products in another order. Over the ~100-term sums of these fields that is a few float ulps of
// the Δs (tests/field's Vulkan tests bound the Δs' relative error by 1e-5); the deformed
// parameters add the canonical value, so 1e-5 of (1 + |value|) holds with margin and a wrong
// plane, head or row order (errors of 1e-2 and more) fails it.
constexpr double kParamTol = 1e-5;

bool HaveVulkan() { return !ListVulkanDevices().empty(); }

// A 60 m street of SH degree 3 Gaussians (a field needs degree 3).
GaussianStore Street(uint64_t seed, size_t n) {
  return MakeSyntheticStreet({.num_gaussians = n, .seed = seed, .sh_degree = 3, .street_length_m = 60});
}

// MovingField with the space-time planes held constant in time over the lower 3/4 of each
// spatial axis: the Gaussians there do not move and the static skip bakes them.
field::DeformationField PartlyStaticField(const GaussianStore& g) {
  field::DeformationField f = MovingField(g, 0, kLogEndUs);
  const field::FieldLayout& L = f.layout();
  std::vector<float>& p = f.mutable_params();
  for (const field::PlaneInfo& pi : L.planes) {
    if (!field::PlaneHasTime(pi.plane)) continue;
    for (int v = 1; v < pi.height; ++v) {
      for (int u = 0; u < pi.width * 3 / 4; ++u) {
        std::copy_n(&p[pi.offset + static_cast<size_t>(u) * L.channels], L.channels,
                    &p[pi.offset + (static_cast<size_t>(v) * pi.width + u) * L.channels]);
      }
    }
  }
  return f;
}

double WorstRelDiff(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  double worst = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) {
    worst = std::max(worst, std::abs(double(a[i]) - b[i]) / (1.0 + std::abs(double(b[i]))));
  }
  return worst;
}

void ExpectStoresClose(const GaussianStore& vk, const GaussianStore& cpu, const std::string& tag) {
  EXPECT_LT(WorstRelDiff(vk.means, cpu.means), kParamTol) << tag;
  EXPECT_LT(WorstRelDiff(vk.sh, cpu.sh), kParamTol) << tag;
  EXPECT_LT(WorstRelDiff(vk.log_scales, cpu.log_scales), kParamTol) << tag;
  EXPECT_LT(WorstRelDiff(vk.rotations, cpu.rotations), kParamTol) << tag;
  EXPECT_LT(WorstRelDiff(vk.opacity_logits, cpu.opacity_logits), kParamTol) << tag;
}

void ExpectStoresEqual(const GaussianStore& a, const GaussianStore& b, const std::string& tag) {
  EXPECT_TRUE(a.means == b.means && a.sh == b.sh && a.log_scales == b.log_scales && a.rotations == b.rotations &&
              a.opacity_logits == b.opacity_logits)
      << tag;
}

field::VulkanFieldOptions Lavapipe() {
  field::VulkanFieldOptions o;
  o.device = VulkanDevicePreference::kLavapipe;
  return o;
}

// A device hook that counts its calls.
template <typename Device>
Device Counted(Device d, std::shared_ptr<int> calls) {
  d.forward = [f = std::move(d.forward), calls](const auto&... args) {
    ++*calls;
    return f(args...);
  };
  return d;
}

// Both serving fields side by side, cpu and Vulkan, over kTimesUs. make(options, pool, device):
// device null for the cpu one; the Vulkan one gets its hook at creation (the static analysis runs
// on the device: counted) or, with `late`, after it (ServeOnVulkan).
template <typename Make>
void CompareCpuAndVulkan(const Make& make, const std::string& name, bool expect_static = true) {
  ThreadPool pool(0);
  for (bool skip : {true, false}) {
    for (bool late : {false, true}) {
      field::StaticSkipOptions o;
      o.enabled = skip;
      auto cpu = make(o, pool, nullptr);
      auto calls = std::make_shared<int>(0);
      auto vk = late ? make(o, pool, nullptr) : make(o, pool, &calls);
      if (late) field::ServeOnVulkan(*vk, Lavapipe());
      const std::string tag = name + (skip ? " skip" : " no-skip") + (late ? " late" : "");
      if (skip && !late) {
        EXPECT_GE(*calls, 2) << tag << ": the static analysis did not run on the device";
      }
      EXPECT_EQ(vk->num_dynamic(), cpu->num_dynamic()) << tag;
      if (skip && expect_static) {
        EXPECT_GT(vk->size() - vk->num_dynamic(), 0u) << tag << ": nothing static, the skip is not tested";
      }
      EXPECT_GT(vk->num_dynamic(), 0u) << tag;
      GaussianStore first;
      for (int64_t t : kTimesUs) {
        absl::StatusOr<const GaussianStore*> a = vk->At(t, pool);
        absl::StatusOr<const GaussianStore*> b = cpu->At(t, pool);
        ASSERT_TRUE(a.ok() && b.ok()) << tag << " " << a.status() << " " << b.status();
        EXPECT_EQ(vk->device(), field::kVulkanServingDevice) << tag << ": the device failed";
        ExpectStoresClose(**a, **b, tag + " t=" + std::to_string(t));
        if (t == kTimesUs[0]) first = **a;
      }
      EXPECT_EQ(vk->field_evaluations(), cpu->field_evaluations()) << tag;
      EXPECT_NE(first.means, (*vk->At(kTimesUs[2], pool))->means) << tag << ": the field does not move";
    }
  }
}

TEST(ServedFieldOnVulkan, S3GaussianEqualsTheCpuWithAndWithoutTheSkip) {
  if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device";
  const GaussianStore g = Street(1, 3000);
  const field::DeformationField f = PartlyStaticField(g);
  CompareCpuAndVulkan(
      [&](const field::StaticSkipOptions& o, ThreadPool& pool, std::shared_ptr<int>* calls) {
        const field::ServingField::Device d =
            calls ? Counted(field::VulkanFieldForward(Lavapipe()), *calls) : field::ServingField::Device{};
        absl::StatusOr<field::ServingField> sf = field::ServingField::Create(f, g, o, pool, calls ? &d : nullptr);
        EXPECT_TRUE(sf.ok()) << sf.status();
        return std::make_unique<field::ServingField>(std::move(*sf));
      },
      "s3gaussian");
}

// Every module but the Fourier time tokens, which move every Gaussian (nothing is static with them).
field::ExtendedFieldConfig NoFourierTime() {
  field::ExtendedFieldConfig c = field::ExtendedFieldConfig::AllOn();
  c.temporal = false;
  return c;
}

TEST(ServedFieldOnVulkan, ExtendedEqualsTheCpuWithAndWithoutTheSkip) {
  if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device";
  const GaussianStore g = Street(2, 2000);
  for (bool temporal : {true, false}) {
    const field::ExtendedField f =
        MovingExtension(PartlyStaticField(g), 3, temporal ? field::ExtendedFieldConfig::AllOn() : NoFourierTime());
    CompareCpuAndVulkan(
        [&](const field::StaticSkipOptions& o, ThreadPool& pool, std::shared_ptr<int>* calls) {
          const field::ExtServingField::Device d =
              calls ? Counted(field::VulkanExtFieldForward(Lavapipe()), *calls) : field::ExtServingField::Device{};
          absl::StatusOr<std::unique_ptr<field::ExtServingField>> sf =
              field::ExtServingField::Create(f, g, o, pool, calls ? &d : nullptr);
          EXPECT_TRUE(sf.ok()) << sf.status();
          return std::move(*sf);
        },
        temporal ? "extended, every module" : "extended, no Fourier time", /*expect_static=*/!temporal);
  }
}

// A device that answers `good_calls` times (with the cpu's formulas on the compact rows, standing in
// for a device) and then fails as a lost device does: the failing timestamp and every later one
// are the cpu's, bit for bit, and no call fails.
TEST(ServedFieldOnVulkan, ADeviceThatFailsFallsBackToTheCpu) {
  const GaussianStore g = Street(3, 1500);
  const field::DeformationField f = PartlyStaticField(g);
  ThreadPool pool(0);
  for (int good_calls : {0, 1}) {
    absl::StatusOr<field::ServingField> cpu = field::ServingField::Create(f, g, {}, pool);
    absl::StatusOr<field::ServingField> dev = field::ServingField::Create(f, g, {}, pool);
    ASSERT_TRUE(cpu.ok() && dev.ok());
    auto calls = std::make_shared<int>(0);
    auto ws = std::make_shared<field::FieldWorkspace>();
    dev->SetDevice("test-device", [calls, good_calls, ws, &pool](
                                      const field::DeformationField& field, const field::FieldQuery& q,
                                      std::span<const float> means, std::vector<float>* dx, std::vector<float>* dsh) {
      if ((*calls)++ >= good_calls) return absl::UnavailableError("device lost (simulated)");
      const size_t n = means.size() / 3;
      dx->resize(n * 3);
      if (dsh) dsh->resize(n * field::kShOutputs);
      field::FieldForward<float>(field.layout(), field.params().data(), q, means.data(), nullptr, n, dx->data(),
                                 dsh ? dsh->data() : nullptr, pool, *ws);
      return absl::OkStatus();
    });
    EXPECT_EQ(dev->device(), "test-device");
    for (int64_t t : kTimesUs) {
      absl::StatusOr<const GaussianStore*> a = dev->At(t, pool);
      absl::StatusOr<const GaussianStore*> b = cpu->At(t, pool);
      ASSERT_TRUE(a.ok() && b.ok()) << a.status();
      if (*calls > good_calls) ExpectStoresEqual(**a, **b, "after the failure, t=" + std::to_string(t));
    }
    EXPECT_EQ(*calls, good_calls + 1) << "the failed device was called again";
    EXPECT_EQ(dev->device(), "cpu");
  }
  // A device that fails during the static analysis: the analysis is redone on the cpu and the
  // scene stays there, bit for bit the cpu's.
  {
    auto calls = std::make_shared<int>(0);
    const field::ServingField::Device failing{
        "test-device", [calls](const field::DeformationField&, const field::FieldQuery&, std::span<const float>,
                               std::vector<float>*, std::vector<float>*) {
          ++*calls;
          return absl::UnavailableError("device lost (simulated)");
        }};
    absl::StatusOr<field::ServingField> cpu = field::ServingField::Create(f, g, {}, pool);
    absl::StatusOr<field::ServingField> dev = field::ServingField::Create(f, g, {}, pool, &failing);
    ASSERT_TRUE(cpu.ok() && dev.ok()) << dev.status();
    EXPECT_EQ(*calls, 1);
    EXPECT_EQ(dev->device(), "cpu");
    EXPECT_EQ(dev->num_dynamic(), cpu->num_dynamic());
    for (int64_t t : kTimesUs) ExpectStoresEqual(**dev->At(t, pool), **cpu->At(t, pool), "analysis failure");
    EXPECT_EQ(*calls, 1) << "the failed device was called again";
  }
  // The extended field's hook the same way (failing at once).
  const field::ExtendedField ext = MovingExtension(f, 4);
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> cpu = field::ExtServingField::Create(ext, g, {}, pool);
  absl::StatusOr<std::unique_ptr<field::ExtServingField>> dev = field::ExtServingField::Create(ext, g, {}, pool);
  ASSERT_TRUE(cpu.ok() && dev.ok());
  (*dev)->SetDevice("test-device", [](const field::ExtendedField&, const field::ExtPass&,
                                      const field::ExtInputs<float>&,
                                      const field::ExtOutputs<float>&) -> absl::StatusOr<double> {
    return absl::ResourceExhaustedError("out of device memory (simulated)");
  });
  for (int64_t t : kTimesUs) {
    absl::StatusOr<const GaussianStore*> a = (*dev)->At(t, pool);
    absl::StatusOr<const GaussianStore*> b = (*cpu)->At(t, pool);
    ASSERT_TRUE(a.ok() && b.ok()) << a.status();
    ExpectStoresEqual(**a, **b, "extended t=" + std::to_string(t));
  }
  EXPECT_EQ((*dev)->device(), "cpu");
}

// The exact field of `f` over `g` served on the cpu (no skip options).
std::unique_ptr<field::ServingField> ExactServed(const field::DeformationField& f, const GaussianStore& g,
                                                 ThreadPool& pool) {
  absl::StatusOr<field::ServingField> served = field::ServingField::Create(f, g, {}, pool);
  EXPECT_TRUE(served.ok()) << served.status();
  return std::make_unique<field::ServingField>(std::move(*served));
}

// The RGB of FrontCamera(0) rendered from `scene` by `engine`.
std::vector<float> FrontRgb(Engine& engine, const DeviceScene& scene) {
  RenderOutput out;
  EXPECT_TRUE(engine.Render(scene, FrontCamera(0.0), RenderOptions{}, &out).ok());
  return out.rgb;
}

// Stands in for the serving form's kernel in DynamicSceneField: its "writes" put every
// Gaussian, the static ones too, 3 m up (not the scene at any time), and the call numbered
// `fail_at` fails.
class ShiftingWriter : public field::DeviceSceneWriter {
 public:
  ShiftingWriter(Engine& engine, GaussianStore scene, int fail_at, std::shared_ptr<int> calls)
      : engine_(engine), shifted_(std::move(scene)), fail_at_(fail_at), calls_(std::move(calls)) {
    for (size_t i = 0; i < shifted_.size(); ++i) shifted_.means[i * 3 + 2] += 3.0f;
  }
  absl::Status WriteAt(int64_t, DeviceScene* scene) override {
    if ((*calls_)++ == fail_at_) return absl::UnavailableError("device lost (simulated)");
    // The cpu engine updates its copy in place; the scene stays DynamicSceneField's.
    std::unique_ptr<DeviceScene> held(scene);
    const absl::Status s = engine_.UpdateSceneParams(ParamsViewOf(shifted_), &held);
    if (held.release() != scene) return absl::InternalError("the engine replaced the scene");
    return s;
  }
  std::string device() const override { return "test-writer"; }

 private:
  Engine& engine_;
  GaussianStore shifted_;
  const int fail_at_;
  std::shared_ptr<int> calls_;
};

// A writer that fails mid-serving (the kernel's device lost): DynamicSceneField drops it and
// serves the host form with a whole-scene upload, so what the engine renders equals a host-only
// field's at the failing time and after, whatever the writer left in the engine's copy (a
// fall-back that updated only the moving rows would keep the static Gaussians 3 m up); the
// writer is not called again and stats name the host. No writer (an error making it, or none for
// the engine) leaves the scene on the host from the start.
TEST(DynamicSceneFieldWriter, AWriterThatFailsFallsBackToTheHostWithAWholeUpload) {
  const GaussianStore g = Street(4, 1500);
  const field::DeformationField f = PartlyStaticField(g);
  ThreadPool pool(0);
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(engine.ok()) << engine.status();
  const server::SceneUploader upload = [&](const GaussianStore& s) { return (*engine)->Upload(s); };
  auto make = [&](server::DeviceWriterMaker writer) {
    std::unique_ptr<field::ServingField> served = ExactServed(f, g, pool);
    EXPECT_GT(served->num_dynamic(), 0u);
    EXPECT_LT(served->num_dynamic(), g.size()) << "the test needs static Gaussians";
    absl::StatusOr<std::unique_ptr<server::DynamicSceneField>> d =
        server::DynamicSceneField::Create(std::move(served), std::nullopt, upload, std::move(writer));
    EXPECT_TRUE(d.ok()) << d.status();
    return std::move(*d);
  };
  auto render = [&](const DeviceScene& scene) { return FrontRgb(**engine, scene); };
  std::unique_ptr<server::DynamicSceneField> host = make({});
  auto calls = std::make_shared<int>(0);
  std::unique_ptr<server::DynamicSceneField> kernel = make([&](Engine& e, const field::ServedScene&, ThreadPool&) {
    return absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>>(
        std::make_unique<ShiftingWriter>(e, g, /*fail_at=*/1, calls));
  });
  absl::StatusOr<const DeviceScene*> first = kernel->At(kTimesUs[1], **engine);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(kernel->stats().device, "test-writer");
  absl::StatusOr<const DeviceScene*> first_host = host->At(kTimesUs[1], **engine);
  ASSERT_TRUE(first_host.ok());
  EXPECT_NE(render(**first), render(**first_host)) << "the writer's scene must differ for the test to bite";
  for (int64_t t : {kTimesUs[2], kTimesUs[3], kTimesUs[0]}) {
    absl::StatusOr<const DeviceScene*> a = kernel->At(t, **engine);
    ASSERT_TRUE(a.ok()) << a.status();
    const std::vector<float> from_kernel = render(**a);
    absl::StatusOr<const DeviceScene*> b = host->At(t, **engine);
    ASSERT_TRUE(b.ok());
    EXPECT_EQ(from_kernel, render(**b)) << "t=" << t;
  }
  EXPECT_EQ(*calls, 2) << "the failed writer was called again";
  EXPECT_EQ(kernel->stats().device, "cpu");

  // No writer: an error, or none for this engine (DeviceWriterFor on a cpu engine).
  for (bool fails : {true, false}) {
    std::unique_ptr<server::DynamicSceneField> unmade = make([fails](Engine&, const field::ServedScene&, ThreadPool&) {
      return fails ? absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>>(absl::UnimplementedError("no kernel"))
                   : absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>>(nullptr);
    });
    absl::StatusOr<const DeviceScene*> a = unmade->At(kTimesUs[2], **engine);
    ASSERT_TRUE(a.ok()) << a.status();
    const std::vector<float> from_unmade = render(**a);
    EXPECT_EQ(from_unmade, render(**host->At(kTimesUs[2], **engine))) << fails;
    EXPECT_EQ(unmade->stats().device, "cpu");
  }
}

// The cpu engine's writer (field::HostPlanesWriter): the serving form written straight into the
// engine's planes renders as the host form uploaded, at every time and back again; a served
// dynamic scene with it renders as one without it, and its LiDAR geometry is the host's. No
// writer for the exact field or for another engine's scenes.
TEST(HostPlanesWriter, TheFormWrittenIntoTheCpuEnginesPlanesRendersAsTheHostForm) {
  const GaussianStore g = Street(6, 1500);
  const field::DeformationField f = PartlyStaticField(g);
  ThreadPool pool(0);
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  ASSERT_TRUE(engine.ok()) << engine.status();
  auto form_of = [&] {
    std::unique_ptr<field::ServingField> e = ExactServed(f, g, pool);
    absl::StatusOr<std::unique_ptr<field::ServingForm>> form = field::ServingForm::Build(*e, {}, pool);
    EXPECT_TRUE(form.ok()) << form.status();
    return std::move(*form);
  };
  auto render = [&](const DeviceScene& scene) { return FrontRgb(**engine, scene); };
  std::unique_ptr<field::ServingForm> form = form_of();
  ASSERT_GT(form->num_dynamic(), 0u);
  ASSERT_LT(form->num_dynamic(), g.size());
  absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>> writer = field::HostPlanesWriterFor(**engine, *form, pool);
  ASSERT_TRUE(writer.ok() && *writer) << writer.status();
  EXPECT_EQ((*writer)->device(), "cpu");
  absl::StatusOr<std::unique_ptr<DeviceScene>> written = (*engine)->Upload(**form->At(kTimesUs[0], pool));
  ASSERT_TRUE(written.ok());
  std::vector<float> first;
  for (int64_t t : {kTimesUs[1], kTimesUs[2], kTimesUs[3], kTimesUs[0]}) {
    ASSERT_TRUE((*writer)->WriteAt(t, written->get()).ok()) << t;
    absl::StatusOr<std::unique_ptr<DeviceScene>> uploaded = (*engine)->Upload(**form->At(t, pool));
    ASSERT_TRUE(uploaded.ok());
    const std::vector<float> rgb = render(**written);
    EXPECT_EQ(rgb, render(**uploaded)) << "t=" << t;
    if (first.empty()) first = rgb;
  }
  EXPECT_NE(first, render(**written)) << "the field must move something in view for the test to bite";

  // A scene of another size is refused, not written past its end.
  absl::StatusOr<std::unique_ptr<DeviceScene>> small = (*engine)->Upload(Street(7, 100));
  ASSERT_TRUE(small.ok());
  EXPECT_EQ((*writer)->WriteAt(kTimesUs[1], small->get()).code(), absl::StatusCode::kInvalidArgument);

  // Served: with the writer (what scene_loading.cc gives a cpu engine) and without.
  const server::SceneUploader upload = [&](const GaussianStore& s) { return (*engine)->Upload(s); };
  absl::StatusOr<std::unique_ptr<server::DynamicSceneField>> planes =
      server::DynamicSceneField::Create(form_of(), std::nullopt, upload, &field::HostPlanesWriterFor);
  absl::StatusOr<std::unique_ptr<server::DynamicSceneField>> host =
      server::DynamicSceneField::Create(form_of(), std::nullopt, upload);
  ASSERT_TRUE(planes.ok() && host.ok());
  for (int64_t t : {kTimesUs[2], kTimesUs[1], kTimesUs[3]}) {
    const int64_t evaluations = (*planes)->stats().field_evaluations;
    absl::StatusOr<const DeviceScene*> a = (*planes)->At(t, **engine);
    ASSERT_TRUE(a.ok()) << a.status();
    const std::vector<float> from_planes = render(**a);
    EXPECT_EQ(from_planes, render(**(*host)->At(t, **engine))) << "t=" << t;
    absl::StatusOr<std::shared_ptr<const server::HostScene>> lidar = (*planes)->GeometryAt(t);
    ASSERT_TRUE(lidar.ok());
    EXPECT_EQ((*lidar)->gaussians().means, (**(*host)->HostAt(t)).gaussians().means) << "t=" << t;
    EXPECT_EQ((*planes)->stats().field_evaluations, evaluations + 1) << "the camera and the LiDAR share a time";
  }
  EXPECT_EQ((*planes)->stats().device, "cpu");

  std::unique_ptr<field::ServingField> not_a_form = ExactServed(f, g, pool);
  absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>> none = field::HostPlanesWriterFor(**engine, *not_a_form, pool);
  EXPECT_TRUE(none.ok() && !*none);
  if (HaveVulkan()) {
    absl::StatusOr<std::unique_ptr<Engine>> vk = CreateEngine(Backend::kVulkan);
    ASSERT_TRUE(vk.ok());
    none = field::HostPlanesWriterFor(**vk, *form, pool);
    EXPECT_TRUE(none.ok() && !*none);
  }
}

constexpr char kRig[] = R"({"cameras": [
  {"sensor_id": "cam_front", "width": 128, "height": 64, "fx": 80, "fy": 80, "cx": 63.5, "cy": 31.5,
   "T_ego_from_cam": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}]})";

// Two servers over one data root ("dyn": S3Gaussian's field, "ext": the extended one, both partly
// static): cpu_ with the default --field-device auto on the cpu engine, and a second one started
// by the test with its own options.
class FieldDeviceServerTest : public ServerTest {
 protected:
  void SetUp() override {
    ServerTest::SetUp();
    const GaussianStore g = Street(5, 3000);
    const field::DeformationField f = PartlyStaticField(g);
    WriteScene("dyn", g, f, nullptr);
    const field::ExtendedField ext = MovingExtension(PartlyStaticField(g), 6, NoFourierTime());
    WriteScene("ext", g, ext.base(), &ext);
    // The exact field on both servers: these tests hold the device's evaluation against the cpu's
    // (the serving form evaluates on the cpu wherever it was built).
    server::ServerOptions o = TestOptions(data_root_, state_dir_);
    o.exact_field = true;
    StartServer(o);  // the cpu one: client_
  }

  void WriteScene(const std::string& name, const GaussianStore& g, const field::DeformationField& f,
                  const field::ExtendedField* ext) {
    const std::string dir = data_root_ + "/" + name;
    fs::create_directories(dir);
    ASSERT_TRUE(WriteGaussianPly(g, dir + "/scene.ply").ok());
    ASSERT_TRUE(field::SaveField(f, dir + "/" + field::kFieldFileName).ok());
    if (ext) {
      ASSERT_TRUE(field::SaveExtendedField(*ext, dir + "/" + field::kExtendedFieldFileName).ok());
    }
    std::ofstream(dir + "/scene.json") << kRig;
  }

  // A server with the field on `device` (the exact field unless `form`) and the engine on
  // `backend`, its state in `state`, and its client.
  RunningServer Start(train::FieldDevice device, const std::string& state, Backend backend = Backend::kCpu,
                bool form = false) {
    server::ServerOptions o = TestOptions(data_root_, state_dir_ + "/" + state);
    o.field_device = device;
    o.exact_field = !form;
    o.backend = backend;
    return StartServerAndClient(o);
  }
  // A second server forced to `device`, and its client.
  void StartOther(train::FieldDevice device) {
    RunningServer r = Start(device, "other");
    ASSERT_TRUE(r.client);
    other_server_ = std::move(r.server);
    other_ = std::move(r.client);
  }

  void TearDown() override {
    other_.reset();
    other_server_.reset();
    ServerTest::TearDown();
  }

  static v1::RenderResponse Render(client::Client& c, const std::string& scene, int64_t time_us) {
    v1::RenderRequest req;
    req.set_scene(scene);
    req.set_time_us(time_us);
    *req.mutable_t_world_from_ego() = client::ToPose(EgoAt(8));
    req.mutable_outputs()->set_rgb(true);
    req.mutable_outputs()->set_depth(true);
    absl::StatusOr<v1::RenderResponse> r = c.Render(req);
    EXPECT_TRUE(r.ok()) << scene << " " << r.status();
    EXPECT_TRUE(!r.ok() || r->frames_size() == 1);
    return r.ok() ? *r : v1::RenderResponse{};
  }

  static std::string FieldDevice(client::Client& c, const std::string& scene) {
    absl::StatusOr<v1::Scene> s = c.GetScene(scene);
    EXPECT_TRUE(s.ok()) << s.status();
    return s.ok() ? s->field_device() : "";
  }

  std::unique_ptr<server::Server> other_server_;
  std::unique_ptr<client::Client> other_;
};

// Served renders: the Gaussians differ by float rounding (kParamTol), which moves a pixel by far
// less than one 8-bit level (~1e-5 relative in depth), except where a Gaussian sits at one of the
// renderer's discrete thresholds (alpha < 1/255 skipped, transmittance < 1e-4 stops): there it
// enters or leaves the blend with alpha ~1/255, moving that pixel's colour by up to ~1 level
// (2 with the byte rounding) and its depth by up to 1/255 of the depth contrast behind it.
// Asserted: RGB within 2 levels with under 1 % of the bytes differing; depth within 1e-2 relative
// with under 1 % of the pixels beyond 1e-4 (measured here: RGB max 1 level on <= 0.01 % of the
// bytes, depth max 1.3e-5; 2.6e-3 on one pixel with the Fourier time tokens on). A field that did
// not run, or ran at another time, changes whole regions by tens of levels and metres.
TEST_F(FieldDeviceServerTest, ForcedVulkanServesTheCpuRendersWithinRounding) {
  if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device";
  StartOther(train::FieldDevice::kVulkan);
  for (const std::string scene : {"dyn", "ext"}) {
    ASSERT_TRUE(client_->LoadScene(scene, true).ok());
    ASSERT_TRUE(other_->LoadScene(scene, true).ok());
    absl::StatusOr<v1::Scene> info = other_->GetScene(scene);
    ASSERT_TRUE(info.ok());
    EXPECT_LT(info->num_dynamic_gaussians(), info->num_gaussians()) << scene << ": the static skip baked nothing";
    std::string previous;
    for (int64_t t : kTimesUs) {
      const v1::RenderResponse vk = Render(*other_, scene, t);
      const v1::RenderResponse cpu = Render(*client_, scene, t);
      if (vk.frames_size() != 1 || cpu.frames_size() != 1) continue;
      const std::string tag = scene + " t=" + std::to_string(t);
      ExpectFramesWithinRounding(vk.frames(0), cpu.frames(0), tag);
      EXPECT_GT(vk.frames(0).num_visible_gaussians(), 50u) << tag;
      if (!previous.empty()) {
        EXPECT_GT(CompareRgb(previous, vk.frames(0).rgb().data()).max, 5) << tag << ": no motion";
      }
      previous = vk.frames(0).rgb().data();
    }
    EXPECT_EQ(FieldDevice(*other_, scene), "vulkan") << scene << ": the device failed";
    // --field-device auto with the cpu engine: the cpu.
    EXPECT_EQ(FieldDevice(*client_, scene), "cpu") << scene;
  }
}

// The serving form on a Vulkan engine with --field-device vulkan: its compute kernel writes the
// engine's copy of the scene at each new time (GetScene's field_device "vulkan"), and the renders
// equal those of the same form (one field.serving cache) evaluated on the host and uploaded
// (--field-device cpu, the same engine) within the rounding bounds above: the kernel's
// multiply-adds may fuse where the host's do not.
TEST_F(FieldDeviceServerTest, TheFormsKernelOnAVulkanEngineServesTheHostFormsRenders) {
  if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device";
  RunningServer host = Start(train::FieldDevice::kCpu, "form_host", Backend::kVulkan, /*form=*/true);
  RunningServer kernel = Start(train::FieldDevice::kVulkan, "form_kernel", Backend::kVulkan, /*form=*/true);
  ASSERT_TRUE(host.client && kernel.client);
  ASSERT_TRUE(host.client->LoadScene("dyn", true).ok());
  ASSERT_TRUE(kernel.client->LoadScene("dyn", true).ok());
  std::string previous;
  int64_t previous_t = -1;
  for (int64_t t : {kTimesUs[1], kTimesUs[0], kTimesUs[2], kTimesUs[2], kTimesUs[3], kLogEndUs + 500'000}) {
    const v1::RenderResponse a = Render(*kernel.client, "dyn", t);
    const v1::RenderResponse b = Render(*host.client, "dyn", t);
    if (a.frames_size() != 1 || b.frames_size() != 1) continue;
    const std::string tag = "t=" + std::to_string(t);
    ExpectFramesWithinRounding(a.frames(0), b.frames(0), tag);
    // A new time (after clamping to the log) moves the picture.
    const int64_t clamped = std::min(t, kLogEndUs);
    if (!previous.empty() && clamped != previous_t) {
      EXPECT_GT(CompareRgb(previous, a.frames(0).rgb().data()).max, 5) << tag << ": no motion";
    }
    previous = a.frames(0).rgb().data();
    previous_t = clamped;
  }
  absl::StatusOr<v1::Scene> k = kernel.client->GetScene("dyn");
  absl::StatusOr<v1::Scene> h = host.client->GetScene("dyn");
  ASSERT_TRUE(k.ok() && h.ok());
  EXPECT_EQ(k->field_device(), "vulkan") << "the kernel failed or was not used";
  EXPECT_EQ(h->field_device(), "cpu");
  EXPECT_EQ(k->field_serving(), "form");
  EXPECT_EQ(h->field_serving(), "form");
}

// No Vulkan device for the field (STREETSIM_VK_DEVICE naming none: Vulkan's own "no such device"
// error, as on a machine without Vulkan): a forced-vulkan server loads and serves every scene on
// the cpu, renders equal to the cpu server's bit for bit.
TEST_F(FieldDeviceServerTest, ForcedVulkanWithoutADeviceFallsBackToTheCpu) {
  const char* saved = std::getenv("STREETSIM_VK_DEVICE");
  const std::string saved_value = saved ? saved : "";
  setenv("STREETSIM_VK_DEVICE", "no-such-device-for-this-test", 1);
  StartOther(train::FieldDevice::kVulkan);
  for (const std::string scene : {"dyn", "ext"}) {
    absl::StatusOr<v1::Scene> loaded = other_->LoadScene(scene, true);
    ASSERT_TRUE(loaded.ok()) << loaded.status();
    EXPECT_EQ(loaded->state(), v1::SCENE_STATE_READY) << loaded->error();
    for (int64_t t : {kTimesUs[1], kTimesUs[2]}) {
      const v1::RenderResponse a = Render(*other_, scene, t);
      const v1::RenderResponse b = Render(*client_, scene, t);
      if (a.frames_size() != 1 || b.frames_size() != 1) continue;
      EXPECT_TRUE(a.frames(0).rgb().data() == b.frames(0).rgb().data()) << scene << " t=" << t;
    }
    EXPECT_EQ(FieldDevice(*other_, scene), "cpu") << scene;
  }
  if (saved) {
    setenv("STREETSIM_VK_DEVICE", saved_value.c_str(), 1);
  } else {
    unsetenv("STREETSIM_VK_DEVICE");
  }
}

TEST(ServeFieldDeviceFlag, BadValuesExit2) {
  const std::string dir = ScratchDir("field_device", "bad_flag");
  for (const std::string bad : {"gpu", "VULKAN", "cpu,vulkan"}) {
    const cli_test::Result r = cli_test::RunStreetsim("serve --listen 127.0.0.1:0 --data-root " + dir +
                                                          " --state-dir " + dir + "/state --field-device '" + bad + "'",
                                                      dir + "/out.txt", dir + "/err.txt");
    EXPECT_EQ(r.code, 2) << bad << ": " << r.err;
    EXPECT_NE(r.err.find("--field-device"), std::string::npos) << r.err;
  }
}

// --field-serving takes served or exact, on serve and on eval (where it needs --served): anything
// else exits 2 naming the flag, before a scene or log is read.
TEST(ServeFieldServingFlag, BadValuesExit2) {
  const std::string dir = ScratchDir("field_device", "bad_serving_flag");
  for (const std::string bad : {"form", "EXACT", "served,exact", ""}) {
    cli_test::Result r = cli_test::RunStreetsim("serve --listen 127.0.0.1:0 --data-root " + dir + " --state-dir " + dir +
                                                    "/state --field-serving '" + bad + "'",
                                                dir + "/out.txt", dir + "/err.txt");
    EXPECT_EQ(r.code, 2) << bad << ": " << r.err;
    EXPECT_NE(r.err.find("--field-serving"), std::string::npos) << r.err;
    r = cli_test::RunStreetsim("eval --scene " + dir + "/none --log " + dir + "/none --served --field-serving '" + bad +
                                   "'",
                               dir + "/out.txt", dir + "/err.txt");
    EXPECT_EQ(r.code, 2) << bad << ": " << r.err;
    EXPECT_NE(r.err.find("--field-serving"), std::string::npos) << r.err;
  }
  const cli_test::Result r = cli_test::RunStreetsim(
      "eval --scene " + dir + "/none --log " + dir + "/none --field-serving exact", dir + "/out.txt", dir + "/err.txt");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("need --served"), std::string::npos) << r.err;
}

}  // namespace
}  // namespace streetsim::testing
