// The Vulkan trainer glue (render/vulkan/field/vulkan_deformed_scene.h) against the cpu glue
// (deformed_scene.h): one deform + backward, then a few fine-stage iterations (deform, a fixed
// quadratic "render" loss on the deformed means / SH, backward, the field's Adam step, re-upload)
// run side by side on the cpu and on Vulkan. Skips without a Vulkan device.
#include <cmath>
#include <cstdio>
#include <numeric>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/field_adam.h"
#include "render/vulkan/field/vulkan_deformed_scene.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

double RelError(const std::vector<float>& ref, const std::vector<float>& x) {
  double num = 0, den = 0;
  for (size_t i = 0; i < ref.size(); ++i) {
    num += (double(ref[i]) - x[i]) * (double(ref[i]) - x[i]);
    den += double(ref[i]) * ref[i];
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

struct Problem {
  DeformationField field;
  std::vector<float> means, sh, target_means, target_sh;
  size_t n = 0;
};

Problem MakeSetup(size_t n) {
  const FieldConfig c = testing::SmallConfig();
  auto f = DeformationField::Create(c, testing::TestAabb(), {0, 1'000'000}, 5);
  EXPECT_TRUE(f.ok());
  Problem s{*std::move(f), {}, {}, {}, {}, n};
  const FieldLayout& L = s.field.layout();
  std::vector<double> p = testing::RandomParams<double>(c, L, 5);
  for (size_t i = 0; i < p.size(); ++i) s.field.mutable_params()[i] = static_cast<float>(p[i]);
  for (double v : testing::RandomMeans<double>(n, n / 8, 6)) s.means.push_back(static_cast<float>(v));
  std::mt19937_64 rng(8);
  std::normal_distribution<float> g(0, 0.3f);
  s.sh.resize(n * kShOutputs);
  for (float& v : s.sh) v = g(rng);
  s.target_means = s.means;
  for (float& v : s.target_means) v += g(rng);
  s.target_sh.resize(n * kShOutputs);
  for (float& v : s.target_sh) v = g(rng);
  return s;
}

// L = 0.5 |means_t - target|^2 + 0.5 |sh_t (active degree) - target|^2: the "render" gradients.
GaussianGrads RenderGrads(const Problem& s, const DeformedScene& d, int degree) {
  const int ka3 = ShCoeffsForDegree(degree) * 3;
  GaussianGrads g;
  g.means.resize(s.n * 3);
  g.sh.resize(s.n * ka3);
  for (size_t i = 0; i < s.n * 3; ++i) g.means[i] = d.means[i] - s.target_means[i];
  for (size_t i = 0; i < s.n; ++i)
    for (int k = 0; k < ka3; ++k) g.sh[i * ka3 + k] = d.sh[i * kShOutputs + k] - s.target_sh[i * kShOutputs + k];
  return g;
}

class VulkanDeformedScene : public ::testing::Test {
 protected:
  void SetUp() override {
    if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device on this machine";
  }
  ThreadPool pool_{1};
  FieldWorkspace ws_;
};

TEST_F(VulkanDeformedScene, DeformAndBackwardMatchCpuGlue) {
  const Problem s = MakeSetup(64);
  auto vf = VulkanField::Create(s.field);
  ASSERT_TRUE(vf.ok()) << vf.status();
  const CanonicalView cv{s.n, s.means.data(), s.sh.data()};
  const double t = s.field.TimeCoordinate(300'000);
  DeformedScene dc, dv;
  ASSERT_TRUE(DeformScene(s.field, t, cv, pool_, ws_, &dc).ok());
  ASSERT_TRUE(VulkanDeformScene(**vf, s.field, t, cv, pool_, &dv).ok());
  EXPECT_EQ(dv.time_coord, dc.time_coord);
  EXPECT_LT(RelError(dc.dx, dv.dx), 1e-5);
  EXPECT_LT(RelError(dc.dsh, dv.dsh), 1e-5);
  EXPECT_LT(RelError(dc.means, dv.means), 1e-6);
  EXPECT_LT(RelError(dc.sh, dv.sh), 1e-6);
  FieldHyper h;
  h.lambda_dx = 0.05;  // large enough to matter next to the render terms
  h.lambda_dsh = 0.05;
  for (int degree : {1, 3}) {
    GaussianGrads gc = RenderGrads(s, dc, degree), gv = RenderGrads(s, dv, degree);
    std::vector<float> fc, fv, scratch;
    auto lc = DeformBackward(s.field, cv, dc, degree, h, pool_, ws_, &gc, &fc);
    auto lv = VulkanDeformBackward(**vf, s.field, cv, dv, degree, h, pool_, &gv, &fv, &scratch);
    ASSERT_TRUE(lc.ok() && lv.ok());
    EXPECT_NEAR(lv->weighted, lc->weighted, 1e-6 * std::abs(lc->weighted));
    std::printf("degree %d: d_field rel err %.2e, canonical means %.2e\n", degree, RelError(fc, fv),
                RelError(gc.means, gv.means));
    EXPECT_LT(RelError(fc, fv), 1e-5);
    EXPECT_LT(RelError(gc.means, gv.means), 1e-5);
    EXPECT_EQ(gv.sh, RenderGrads(s, dv, degree).sh);  // unchanged by the glue
  }
  GaussianGrads bad = RenderGrads(s, dv, 3);
  bad.means.pop_back();
  std::vector<float> f, scratch;
  EXPECT_FALSE(VulkanDeformBackward(**vf, s.field, cv, dv, 3, h, pool_, &bad, &f, &scratch).ok());
}

// The fine stage's per-iteration order (deform, render gradients, glue backward, Adam, re-upload)
// on both backends: the fields' parameter updates agree.
TEST_F(VulkanDeformedScene, FineIterationsAgreeWithCpu) {
  const Problem s = MakeSetup(96);
  DeformationField cpu_field = s.field, vk_field = s.field;
  auto vf = VulkanField::Create(vk_field);
  ASSERT_TRUE(vf.ok()) << vf.status();
  const CanonicalView cv{s.n, s.means.data(), s.sh.data()};
  FieldHyper h;
  FieldAdamState ac, av;
  ac.Init(s.field.layout().total);
  av.Init(s.field.layout().total);
  std::vector<float> fc, fv, scratch;
  const int kIterations = 4;
  for (int it = 1; it <= kIterations; ++it) {
    const int64_t time_us = 150'000 * it;
    DeformedScene dc, dv;
    ASSERT_TRUE(DeformScene(cpu_field, cpu_field.TimeCoordinate(time_us), cv, pool_, ws_, &dc).ok());
    ASSERT_TRUE(VulkanDeformScene(**vf, vk_field, vk_field.TimeCoordinate(time_us), cv, pool_, &dv).ok());
    GaussianGrads gc = RenderGrads(s, dc, 3), gv = RenderGrads(s, dv, 3);
    std::fill(fc.begin(), fc.end(), 0.0f);
    std::fill(fv.begin(), fv.end(), 0.0f);
    ASSERT_TRUE(DeformBackward(cpu_field, cv, dc, 3, h, pool_, ws_, &gc, &fc).ok());
    ASSERT_TRUE(VulkanDeformBackward(**vf, vk_field, cv, dv, 3, h, pool_, &gv, &fv, &scratch).ok());
    const FieldLrs lrs = FieldLearningRates(h, it, 10.0);
    FieldAdamStep(cpu_field.layout(), cpu_field.mutable_params().data(), fc.data(), &ac, lrs, pool_);
    FieldAdamStep(vk_field.layout(), vk_field.mutable_params().data(), fv.data(), &av, lrs, pool_);
    ASSERT_TRUE((*vf)->UpdateParams(vk_field.params()).ok());
    EXPECT_LT(RelError(gc.means, gv.means), 1e-4) << "iteration " << it;
  }
  // Adam with eps 1e-15 moves every parameter with a non-zero gradient by about the learning rate
  // whatever the gradient's size, so compare the updates, not the parameters.
  std::vector<float> uc(s.field.params().size()), uv(uc.size());
  for (size_t i = 0; i < uc.size(); ++i) {
    uc[i] = cpu_field.params()[i] - s.field.params()[i];
    uv[i] = vk_field.params()[i] - s.field.params()[i];
  }
  std::printf("parameter updates after %d iterations: rel err %.2e (norm %.3e)\n", kIterations, RelError(uc, uv),
              std::sqrt(std::inner_product(uc.begin(), uc.end(), uc.begin(), 0.0)));
  EXPECT_LT(RelError(uc, uv), 1e-4);
  DeformedScene dc, dv;
  ASSERT_TRUE(DeformScene(cpu_field, 0.1, cv, pool_, ws_, &dc).ok());
  ASSERT_TRUE(VulkanDeformScene(**vf, vk_field, 0.1, cv, pool_, &dv).ok());
  EXPECT_LT(RelError(dc.dx, dv.dx), 1e-4);
}

}  // namespace
}  // namespace streetsim::field
