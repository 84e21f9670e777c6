// The vulkan LiDAR backward pass (VulkanLidarRenderer::Backward, render/vulkan/lidar_backward_vk.h)
// on lavapipe: gradients against the cpu double-precision reference (RenderLidarReference with
// upstream gradients) on small random scenes around the sensor (a fifth of them on the seam behind
// it), static and rolling sweeps; against the cpu scalar float backward on a street with saturated
// rays; the compare-and-swap fallback; the deterministic mode (the same checks, and identical bits
// across calls, sweeps and renderers on the street); the preconditions. Relative error per parameter group
// (||a - b|| / ||b||), the style of tests/lidar/lidar_backward_test.cc and
// tests/render/vulkan_backward_test.cc. ctest also runs it at lavapipe subgroup sizes 4 and 16.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "render/lidar/lidar_backward.h"
#include "render/lidar/lidar_renderer.h"
#include "render/vulkan/lidar_renderer_vk.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/common/needle_splats.h"
#include "tests/lidar/lidar_test_scenes.h"

namespace streetsim {
namespace {

VulkanLidarRenderer* MakeRenderer(bool cas) {
  if (cas) setenv("STREETSIM_VK_NO_FLOAT_ATOMICS", "1", 1);
  auto created = VulkanLidarRenderer::Create(VulkanDevicePreference::kLavapipe);
  if (cas) unsetenv("STREETSIM_VK_NO_FLOAT_ATOMICS");
  if (!created.ok()) {
    ADD_FAILURE() << "no vulkan LiDAR renderer: " << created.status();
    std::abort();
  }
  return created->release();
}

// One renderer per atomics mode for the whole binary: device and pipeline creation dominate.
VulkanLidarRenderer& Vk() {
  static VulkanLidarRenderer* r = MakeRenderer(false);
  return *r;
}
VulkanLidarRenderer& VkCas() {
  static VulkanLidarRenderer* r = MakeRenderer(true);
  return *r;
}

struct Scene {
  GaussianStore store;
  std::vector<float> reflectance;
  LidarModel model;
  LidarSweepPose sweep;
  std::vector<float> w_range, w_alpha, w_intensity;  // upstream gradients per ray
};

// lidar_backward_test.cc's gradient-check scene, with the upstream gradients as floats.
Scene RandomScene(unsigned seed, int n, bool rolling) {
  lidar_test::GradScene g = lidar_test::RandomGradScene(seed, n, rolling);
  auto f = [](const std::vector<double>& v) { return std::vector<float>(v.begin(), v.end()); };
  return {std::move(g.store), std::move(g.reflectance), g.model, g.sweep, f(g.w_range), f(g.w_alpha), f(g.w_intensity)};
}

using Grads = LidarGaussianGradsT<double>;

Grads ToDouble(const LidarGaussianGrads& g) {
  auto d = [](const std::vector<float>& v) { return std::vector<double>(v.begin(), v.end()); };
  return {d(g.means), d(g.log_scales), d(g.rotations), d(g.opacity_logits), d(g.reflectance)};
}

// The vulkan backward after a kept vulkan forward; num_visible: the forward's splat count.
Grads VulkanGrads(VulkanLidarRenderer& vk, const GaussianStore& store, const LidarModel& model,
                  const LidarSweepPose& sweep, const std::vector<float>& refl, const LidarUpstreamGrads& up,
                  size_t* num_visible = nullptr, bool deterministic = false) {
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  opt.keep_for_backward = true;
  LidarRenderOutput out;
  absl::Status st = vk.Render(store, model, sweep, opt, &out);
  EXPECT_TRUE(st.ok()) << st;
  if (num_visible) *num_visible = out.num_visible;
  LidarGaussianGrads g;
  st = vk.Backward(up, &g, deterministic);
  EXPECT_TRUE(st.ok()) << st;
  return ToDouble(g);
}

// The cpu float backward after a kScalar forward (the scalar reference backward), or after a
// vectorised one (the vectorised backward).
Grads CpuGrads(const GaussianStore& store, const LidarModel& model, const LidarSweepPose& sweep,
               const std::vector<float>& refl, const LidarUpstreamGrads& up, size_t* saturated = nullptr,
               LidarRenderOptions::Kernel kernel = LidarRenderOptions::Kernel::kScalar) {
  LidarRenderer renderer(2);
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  opt.kernel = kernel;
  opt.keep_for_backward = true;
  LidarRenderOutput out;
  EXPECT_TRUE(renderer.Render(store, model, sweep, opt, &out).ok());
  if (saturated) {
    *saturated = 0;
    for (float a : out.alpha) *saturated += a > 0.999f;
  }
  LidarGaussianGrads g;
  const absl::Status st = renderer.Backward(up, &g);
  EXPECT_TRUE(st.ok()) << st;
  return ToDouble(g);
}

struct Group {
  const char* name;
  std::vector<double> Grads::*grads;
};
const Group kGroups[] = {{"means", &Grads::means},
                         {"log_scales", &Grads::log_scales},
                         {"rotations", &Grads::rotations},
                         {"opacity_logits", &Grads::opacity_logits},
                         {"reflectance", &Grads::reflectance}};

double RelError(const std::vector<double>& a, const std::vector<double>& ref) {
  EXPECT_EQ(a.size(), ref.size());
  double num = 0, den = 0;
  for (size_t i = 0; i < a.size() && i < ref.size(); ++i) {
    num += (a[i] - ref[i]) * (a[i] - ref[i]);
    den += ref[i] * ref[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

class VulkanLidarBackwardSweep : public ::testing::TestWithParam<bool> {};

// Against the double reference's analytic gradients (themselves checked against finite
// differences in lidar_backward_test.cc), beside the cpu float backward's error for scale.
TEST_P(VulkanLidarBackwardSweep, MatchesTheDoubleReference) {
  const bool rolling = GetParam();
  ThreadPool pool(2);
  const Scene s = RandomScene(rolling ? 21 : 17, 300, rolling);
  LidarReferenceOutput ref_out;
  const std::vector<double> wr(s.w_range.begin(), s.w_range.end()), wa(s.w_alpha.begin(), s.w_alpha.end()),
      wi(s.w_intensity.begin(), s.w_intensity.end());
  const LidarUpstreamGradsT<double> up_d{wr.data(), wa.data(), wi.data()};
  Grads ref;
  ASSERT_TRUE(RenderLidarReference(pool, s.store, s.model, s.sweep, &s.reflectance, &ref_out, &up_d, &ref).ok());
  const LidarUpstreamGrads up{s.w_range.data(), s.w_alpha.data(), s.w_intensity.data()};
  size_t visible = 0;
  const Grads vk = VulkanGrads(Vk(), s.store, s.model, s.sweep, s.reflectance, up, &visible);
  const Grads cpu = CpuGrads(s.store, s.model, s.sweep, s.reflectance, up);
  const Grads det = VulkanGrads(Vk(), s.store, s.model, s.sweep, s.reflectance, up, nullptr, true);
  // Most Gaussians drawn, and seam copies among the splats (more splats than drawn Gaussians).
  size_t drawn = 0;
  for (double v : ref.opacity_logits) drawn += v != 0;
  EXPECT_GE(drawn, 250u);
  EXPECT_GT(visible, drawn);
  for (const Group& g : kGroups) {
    const double e_vk = RelError(vk.*(g.grads), ref.*(g.grads));
    const double e_cpu = RelError(cpu.*(g.grads), ref.*(g.grads));
    const double e_det = RelError(det.*(g.grads), ref.*(g.grads));
    std::printf("%s %-15s rel. error vs double reference: vulkan %.2e  deterministic %.2e  cpu "
                "float %.2e\n", rolling ? "rolling" : "static ", g.name, e_vk, e_det, e_cpu);
    EXPECT_LT(e_vk, 1e-4) << g.name;
    EXPECT_LT(e_det, 1e-4) << g.name << " deterministic";
  }
}

INSTANTIATE_TEST_SUITE_P(Sweeps, VulkanLidarBackwardSweep, ::testing::Values(false, true),
                         [](const auto& info) { return info.param ? "Rolling" : "Static"; });

// Needle splats (one axis kilometres long, the others millimetres): the LiDAR projection and its
// backward share the camera's covariance chain (projection_math.h: ProjectCovariance), which
// must neither cancel nor overflow in float on either backend.
TEST(VulkanLidarBackward, NeedleSplatsAgreeWithTheDoubleReference) {
  ThreadPool pool(2);
  Scene s = RandomScene(23, 300, false);
  std::mt19937 rng(23);
  testing::MakeNeedles(7.5f, 2.5f, rng, &s.store);
  const std::vector<double> wr(s.w_range.begin(), s.w_range.end()), wa(s.w_alpha.begin(), s.w_alpha.end()),
      wi(s.w_intensity.begin(), s.w_intensity.end());
  const LidarUpstreamGradsT<double> up_d{wr.data(), wa.data(), wi.data()};
  LidarReferenceOutput ref_out;
  Grads ref;
  ASSERT_TRUE(RenderLidarReference(pool, s.store, s.model, s.sweep, &s.reflectance, &ref_out, &up_d, &ref).ok());
  const LidarUpstreamGrads up{s.w_range.data(), s.w_alpha.data(), s.w_intensity.data()};
  const Grads vk = VulkanGrads(Vk(), s.store, s.model, s.sweep, s.reflectance, up);
  const Grads scalar = CpuGrads(s.store, s.model, s.sweep, s.reflectance, up);
  const Grads simd = CpuGrads(s.store, s.model, s.sweep, s.reflectance, up, nullptr, LidarRenderOptions::Kernel::kSimd);
  size_t drawn = 0;
  for (double v : ref.opacity_logits) drawn += v != 0;
  EXPECT_GE(drawn, 100u);
  for (const Group& g : kGroups) {
    const double e_vk = RelError(vk.*(g.grads), ref.*(g.grads));
    const double e_scalar = RelError(scalar.*(g.grads), ref.*(g.grads));
    const double e_simd = RelError(simd.*(g.grads), ref.*(g.grads));
    std::printf("needles %-15s rel. error vs double reference: vulkan %.2e  cpu scalar %.2e  cpu simd %.2e\n",
                g.name, e_vk, e_scalar, e_simd);
    // Float's own error on needles (the blend's quadratic form of a near-degenerate conic) is
    // ~1e-2; the cancelling chain this guards against gave 1e4 or nan.
    EXPECT_LT(e_vk, 0.1) << g.name;
    EXPECT_LT(e_scalar, 0.1) << g.name;
    EXPECT_LT(e_simd, 0.1) << g.name;
  }
}

// A street (rays that saturate: the T < 1e-4 stop), rolling sweep, reflectance, all three upstream
// gradients, against the cpu scalar backward. The two forwards differ in rounding (a threshold
// can flip on a few rays), so the whole vector per group is compared, as the cpu's own
// VectorisedBackwardMatchesTheScalarReference (bound 1e-2 there; 1e-3 here).
using Street = lidar_test::StreetBackwardCase;
const Street& TheStreet() { return lidar_test::StreetBackward(); }

// The deterministic mode on the street (thousands of splats per tile, where two atomic passes
// differ in their last bits): identical bits across two Backward calls on one kept sweep, a
// second sweep, and a freshly created renderer; the atomic mode's gradients up to rounding.
TEST(VulkanLidarBackward, DeterministicIdenticalBitsOnAStreet) {
  const Street& t = TheStreet();
  LidarRenderOptions opt;
  opt.reflectance = &t.refl;
  opt.keep_for_backward = true;
  LidarRenderOutput out;
  ASSERT_TRUE(Vk().Render(t.store, t.model, t.sweep, opt, &out).ok());
  LidarGaussianGrads a, b, atomic[2];
  ASSERT_TRUE(Vk().Backward(t.up(), &a, true).ok());
  ASSERT_TRUE(Vk().Backward(t.up(), &b, true).ok());
  ASSERT_TRUE(Vk().Backward(t.up(), &atomic[0]).ok());
  ASSERT_TRUE(Vk().Backward(t.up(), &atomic[1]).ok());
  LidarGaussianGrads c;
  ASSERT_TRUE(Vk().Render(t.store, t.model, t.sweep, opt, &out).ok());
  ASSERT_TRUE(Vk().Backward(t.up(), &c, true).ok());
  std::unique_ptr<VulkanLidarRenderer> fresh(MakeRenderer(false));
  LidarGaussianGrads d;
  ASSERT_TRUE(fresh->Render(t.store, t.model, t.sweep, opt, &out).ok());
  ASSERT_TRUE(fresh->Backward(t.up(), &d, true).ok());
  std::printf("street: %zu splats, %zu tile instances\n", out.num_visible, out.num_tile_instances);
  using Field = std::vector<float> LidarGaussianGrads::*;
  const std::pair<const char*, Field> fields[] = {
      {"means", &LidarGaussianGrads::means}, {"log_scales", &LidarGaussianGrads::log_scales},
      {"rotations", &LidarGaussianGrads::rotations},
      {"opacity_logits", &LidarGaussianGrads::opacity_logits},
      {"reflectance", &LidarGaussianGrads::reflectance}};
  auto bit_differences = [](const std::vector<float>& x, const std::vector<float>& y) {
    if (x.size() != y.size()) return x.size() + y.size() + 1;
    size_t n = 0;
    for (size_t i = 0; i < x.size(); ++i) n += std::memcmp(&x[i], &y[i], sizeof(float)) != 0;
    return n;
  };
  for (const auto& [name, field] : fields) {
    EXPECT_EQ(bit_differences(a.*field, b.*field), 0u) << name << ": second call";
    EXPECT_EQ(bit_differences(a.*field, c.*field), 0u) << name << ": second sweep";
    EXPECT_EQ(bit_differences(a.*field, d.*field), 0u) << name << ": fresh renderer";
    auto dbl = [](const std::vector<float>& v) { return std::vector<double>(v.begin(), v.end()); };
    const double e = RelError(dbl(a.*field), dbl(atomic[0].*field));
    std::printf("street %-15s deterministic vs atomic rel. error %.2e; atomic run to run: %zu of %zu "
                "floats differ\n", name, e, bit_differences(atomic[0].*field, atomic[1].*field),
                (a.*field).size());
    EXPECT_LT(e, 1e-5) << name;
  }
}

TEST(VulkanLidarBackward, MatchesTheCpuBackwardOnAStreet) {
  const Street& t = TheStreet();
  const GaussianStore& store = t.store;
  const std::vector<float>& refl = t.refl;
  const LidarModel& m = t.model;
  const LidarSweepPose& sweep = t.sweep;
  const size_t P = static_cast<size_t>(m.beams()) * m.columns;
  const LidarUpstreamGrads up = t.up();
  size_t saturated = 0;
  const Grads cpu = CpuGrads(store, m, sweep, refl, up, &saturated);
  EXPECT_GT(saturated, P / 20);
  const Grads vk = VulkanGrads(Vk(), store, m, sweep, refl, up);
  for (const Group& g : kGroups) {
    const double e = RelError(vk.*(g.grads), cpu.*(g.grads));
    std::printf("street %-15s rel. difference vulkan vs cpu scalar backward %.2e (%zu saturated rays)\n", g.name,
                e, saturated);
    EXPECT_LT(e, 1e-3) << g.name;
  }
}

// The compare-and-swap blend backward (devices without shaderBufferFloat32AtomicAdd) gives the
// float-atomic one's gradients up to the summation order.
TEST(VulkanLidarBackward, CompareAndSwapFallbackAgrees) {
  const Scene s = RandomScene(9, 300, true);
  const LidarUpstreamGrads up{s.w_range.data(), s.w_alpha.data(), s.w_intensity.data()};
  const Grads a = VulkanGrads(Vk(), s.store, s.model, s.sweep, s.reflectance, up);
  const Grads b = VulkanGrads(VkCas(), s.store, s.model, s.sweep, s.reflectance, up);
  for (const Group& g : kGroups) {
    double norm = 0;
    for (double v : b.*(g.grads)) norm += v * v;
    EXPECT_GT(norm, 0) << g.name;
    EXPECT_LT(RelError(a.*(g.grads), b.*(g.grads)), 1e-5) << g.name;
  }
}

TEST(VulkanLidarBackward, PreconditionsAndNullUpstream) {
  const Scene s = RandomScene(5, 40, false);
  // A renderer of its own: no kept sweep from another test.
  std::unique_ptr<VulkanLidarRenderer> owned(MakeRenderer(false));
  VulkanLidarRenderer& vk = *owned;
  LidarRenderOutput out;
  LidarGaussianGrads g;
  std::vector<float> d(static_cast<size_t>(s.model.beams()) * s.model.columns, 1.0f);
  EXPECT_EQ(vk.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(vk.Render(s.store, s.model, s.sweep, {}, &out).ok());
  EXPECT_EQ(vk.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  LidarRenderOptions opt;
  opt.keep_for_backward = true;
  ASSERT_TRUE(vk.Render(s.store, s.model, s.sweep, opt, &out).ok());
  EXPECT_EQ(vk.Backward({d.data()}, nullptr).code(), absl::StatusCode::kInvalidArgument);
  LidarGaussianGrads det;
  ASSERT_TRUE(vk.Backward({d.data()}, &det, /*deterministic=*/true).ok());
  ASSERT_TRUE(vk.Backward({d.data()}, &g).ok());
  EXPECT_LT(RelError(ToDouble(det).means, ToDouble(g).means), 1e-5);
  EXPECT_EQ(g.means.size(), 3 * s.store.size());
  EXPECT_EQ(g.log_scales.size(), 3 * s.store.size());
  EXPECT_EQ(g.rotations.size(), 4 * s.store.size());
  EXPECT_EQ(g.opacity_logits.size(), s.store.size());
  EXPECT_EQ(g.reflectance.size(), s.store.size());
  // Only range gradients flow: d(sum range_sum) / d(reflectance) is 0.
  for (float v : g.reflectance) EXPECT_EQ(v, 0.0f);
  double norm = 0;
  for (float v : g.means) norm += std::abs(v);
  EXPECT_GT(norm, 0);
  // The same kept sweep twice: the same gradients up to the atomics' summation order.
  LidarGaussianGrads again;
  ASSERT_TRUE(vk.Backward({d.data()}, &again).ok());
  EXPECT_LT(RelError(ToDouble(again).means, ToDouble(g).means), 1e-5);
  // A failed render and a new upload both drop the kept sweep.
  ASSERT_TRUE(vk.Render(s.store, s.model, s.sweep, opt, &out).ok());
  LidarModel bad = s.model;
  bad.columns = 0;
  EXPECT_FALSE(vk.Render(bad, s.sweep, opt, &out).ok());
  EXPECT_EQ(vk.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(vk.Render(s.store, s.model, s.sweep, opt, &out).ok());
  ASSERT_TRUE(vk.Upload(s.store).ok());
  EXPECT_EQ(vk.Backward({d.data()}, &g).code(), absl::StatusCode::kFailedPrecondition);
  // An empty scene: empty gradients.
  GaussianStore empty;
  empty.sh_degree = 0;
  ASSERT_TRUE(vk.Render(empty, s.model, s.sweep, opt, &out).ok());
  ASSERT_TRUE(vk.Backward({d.data()}, &g).ok());
  EXPECT_TRUE(g.means.empty());
  EXPECT_TRUE(g.reflectance.empty());
}

}  // namespace
}  // namespace streetsim
