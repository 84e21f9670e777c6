// The Vulkan field's optimiser on the device (VulkanField::BackwardOnDevice + RegularizeAndStep)
// against the host's (VulkanField::Backward's downloaded gradient + PlaneRegularizers +
// FieldAdamStep): the regularisers' gradient and losses, several Adam steps, the moments' round
// trip, a backward with nothing to propagate, bad sizes. Runs on the first GPU, else lavapipe;
// skips without any Vulkan device.
#include <cmath>
#include <cstdio>
#include <memory>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/field_adam.h"
#include "scene/field/field_regularizers.h"
#include "render/vulkan/field/vulkan_field.h"
#include "scene/optim/adam_kernel.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::RandomMeans;
using testing::RandomParams;
using testing::SmallConfig;
using testing::TestQuery;

double RelError(const std::vector<float>& ref, const std::vector<float>& x) {
  double num = 0, den = 0;
  for (size_t i = 0; i < ref.size(); ++i) {
    const double d = double(ref[i]) - double(x[i]);
    num += d * d;
    den += double(ref[i]) * double(ref[i]);
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

struct Case {
  FieldConfig config;
  FieldLayout L;
  std::vector<float> params, means, gdx, gdsh;
  size_t n = 0;
};

// `time_resolution` 2 makes every space-time plane too short for a second difference (H < 3).
Case MakeCase(size_t n, uint64_t seed, int time_resolution = 5) {
  Case s;
  s.config = SmallConfig();
  s.config.time_resolution = time_resolution;
  s.L = FieldLayout::Make(s.config);
  s.n = n;
  for (double v : RandomParams<double>(s.config, s.L, seed)) s.params.push_back(static_cast<float>(v));
  for (double v : RandomMeans<double>(n, n / 4, seed + 7)) s.means.push_back(static_cast<float>(v));
  testing::RandomOutputGrads(n, seed + 3, &s.gdx, &s.gdsh);
  return s;
}

// The small field's planes over all 4 plane buffers, as the spec's spread over 2 on lavapipe.
VulkanFieldOptions SpreadOptions() {
  VulkanFieldOptions o;
  o.max_plane_buffer_bytes = 2048;
  return o;
}

RegularizerWeights Weights() {
  RegularizerWeights w;  // larger than the spec's so that the terms matter next to the data gradient
  w.plane_tv = 0.3;
  w.time_smoothness = 0.7;
  w.l1_time_planes = 0.05;
  return w;
}

class VulkanFieldOptimizerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device on this machine";
  }
  std::unique_ptr<VulkanField> Make(const Case& s) {
    auto f = VulkanField::Create(s.L, s.params, SpreadOptions());
    EXPECT_TRUE(f.ok()) << f.status();
    return f.ok() ? *std::move(f) : nullptr;
  }
  ThreadPool pool_{1};
};

// With no data gradient (an empty backward) and a zero learning rate the step leaves the
// parameters and turns m into (1 - beta1) * the regularisers' gradient: the device's gradient and
// losses against PlaneRegularizers, on planes with and without a second difference in time.
TEST_F(VulkanFieldOptimizerTest, RegularizerGradientAndLossesMatchTheHost) {
  for (int time_res : {5, 2}) {
    const Case s = MakeCase(64, 5, time_res);
    auto vf = Make(s);
    ASSERT_NE(vf, nullptr);
    ASSERT_GE(vf->plane_buffers(), 3);  // planes in several buffers, as the spec's on lavapipe
    // A real backward first, so that the empty one must replace its gradient by zero.
    std::vector<float> d_means(s.n * 3, 0.0f);
    ASSERT_TRUE(vf->BackwardOnDevice(TestQuery(0.3), s.means, s.gdx, s.gdsh, d_means).ok());
    ASSERT_TRUE(vf->BackwardOnDevice(TestQuery(0.3), s.means, {}, {}, {}).ok());
    absl::StatusOr<RegularizerLosses> dev = vf->RegularizeAndStep(Weights(), FieldLrs{0.0, 0.0}, 1);
    ASSERT_TRUE(dev.ok()) << dev.status();

    std::vector<float> host_grad(s.L.total, 0.0f);
    const RegularizerLosses host = PlaneRegularizers<float>(s.L, s.params.data(), Weights(), host_grad.data(), pool_);
    std::vector<float> m(s.L.total), v(s.L.total), p(s.L.total);
    ASSERT_TRUE(vf->ReadAdamMoments(m, v).ok());
    ASSERT_TRUE(vf->ReadParams(p).ok());
    EXPECT_EQ(p, s.params);
    std::vector<float> dev_grad(s.L.total);
    for (size_t i = 0; i < m.size(); ++i) dev_grad[i] = m[i] / (1 - optim::kAdamBeta1);
    const double e = RelError(host_grad, dev_grad);
    std::printf("time resolution %d: regulariser gradient rel err %.2e; losses %.6g / %.6g / %.6g vs host %.6g / "
                "%.6g / %.6g\n",
                time_res, e, dev->spatial_smoothness, dev->time_smoothness, dev->l1_time, host.spatial_smoothness,
                host.time_smoothness, host.l1_time);
    EXPECT_LT(e, 1e-5);
    EXPECT_GT(host.spatial_smoothness, 0.0);
    EXPECT_NEAR(dev->spatial_smoothness, host.spatial_smoothness, 1e-5 * host.spatial_smoothness);
    EXPECT_NEAR(dev->l1_time, host.l1_time, 1e-5 * host.l1_time);
    if (time_res == 2) {
      EXPECT_EQ(host.time_smoothness, 0.0);
      EXPECT_EQ(dev->time_smoothness, 0.0);
    } else {
      EXPECT_GT(host.time_smoothness, 0.0);
      EXPECT_NEAR(dev->time_smoothness, host.time_smoothness, 1e-5 * host.time_smoothness);
    }
    EXPECT_NEAR(dev->weighted, host.weighted, 1e-5 * host.weighted);
  }
}

// Six steps of backward + regularisers + Adam, one field stepping on the host (gradient
// downloaded, parameters uploaded), one on the device, at decaying learning rates: the parameters
// and moments agree to float rounding after every step.
TEST_F(VulkanFieldOptimizerTest, StepsMatchTheHostOptimizer) {
  const Case s = MakeCase(96, 9);
  auto host_vf = Make(s);
  auto dev_vf = Make(s);
  ASSERT_NE(host_vf, nullptr);
  ASSERT_NE(dev_vf, nullptr);
  std::vector<float> host_params = s.params;
  FieldAdamState adam;
  FieldHyper hyper;
  hyper.lr_decay_steps = 4;
  for (int64_t step = 1; step <= 6; ++step) {
    const FieldQuery q = TestQuery(-0.8 + 0.3 * step);
    const FieldLrs lrs = FieldLearningRates(hyper, step, 20.0);
    std::vector<float> grad(s.L.total, 0.0f), d_means_host(s.n * 3, 0.0f), d_means_dev(s.n * 3, 0.0f);
    ASSERT_TRUE(host_vf->Backward(q, s.means, s.gdx, s.gdsh, grad, d_means_host).ok());
    const RegularizerLosses host = PlaneRegularizers<float>(s.L, host_params.data(), Weights(), grad.data(), pool_);
    FieldAdamStep(s.L, host_params.data(), grad.data(), &adam, lrs, pool_);
    ASSERT_TRUE(host_vf->UpdateParams(host_params).ok());

    ASSERT_TRUE(dev_vf->BackwardOnDevice(q, s.means, s.gdx, s.gdsh, d_means_dev).ok());
    absl::StatusOr<RegularizerLosses> dev = dev_vf->RegularizeAndStep(Weights(), lrs, step);
    ASSERT_TRUE(dev.ok()) << dev.status();
    EXPECT_LT(RelError(d_means_host, d_means_dev), 1e-5);
    EXPECT_NEAR(dev->weighted, host.weighted, 1e-5 * host.weighted);

    std::vector<float> p(s.L.total), m(s.L.total), v(s.L.total);
    ASSERT_TRUE(dev_vf->ReadParams(p).ok());
    ASSERT_TRUE(dev_vf->ReadAdamMoments(m, v).ok());
    std::vector<float> moved(s.L.total), moved_dev(s.L.total);
    for (size_t i = 0; i < p.size(); ++i) {
      moved[i] = host_params[i] - s.params[i];
      moved_dev[i] = p[i] - s.params[i];
    }
    const double e_p = RelError(moved, moved_dev), e_m = RelError(adam.m, m), e_v = RelError(adam.v, v);
    std::printf("step %lld: movement rel err %.2e, m %.2e, v %.2e\n", static_cast<long long>(step), e_p, e_m, e_v);
    EXPECT_LT(e_p, 2e-5);
    EXPECT_LT(e_m, 1e-5);
    EXPECT_LT(e_v, 1e-5);
  }
}

// Moments given to the device come back unchanged; a step from them matches the host's step from
// the same state (a resumed run's first step).
TEST_F(VulkanFieldOptimizerTest, MomentsRoundTripAndResume) {
  const Case s = MakeCase(40, 21);
  auto vf = Make(s);
  ASSERT_NE(vf, nullptr);
  FieldAdamState adam;
  adam.Init(s.L.total);
  std::mt19937_64 rng(4);
  std::uniform_real_distribution<float> u(0.0f, 1e-3f);
  for (size_t i = 0; i < s.L.total; ++i) {
    adam.m[i] = u(rng) - 5e-4f;
    adam.v[i] = u(rng) * 1e-3f;
  }
  adam.step = 41;
  ASSERT_TRUE(vf->SetAdamMoments(adam.m, adam.v).ok());
  std::vector<float> m(s.L.total), v(s.L.total);
  ASSERT_TRUE(vf->ReadAdamMoments(m, v).ok());
  EXPECT_EQ(m, adam.m);
  EXPECT_EQ(v, adam.v);

  const FieldQuery q = TestQuery(0.1);
  const FieldLrs lrs{1e-3, 1e-4};
  std::vector<float> grad(s.L.total, 0.0f);
  ASSERT_TRUE(vf->Backward(q, s.means, s.gdx, s.gdsh, grad, {}).ok());
  std::vector<float> host_params = s.params;
  PlaneRegularizers<float>(s.L, host_params.data(), Weights(), grad.data(), pool_);
  FieldAdamStep(s.L, host_params.data(), grad.data(), &adam, lrs, pool_);
  ASSERT_EQ(adam.step, 42);
  ASSERT_TRUE(vf->BackwardOnDevice(q, s.means, s.gdx, s.gdsh, {}).ok());
  ASSERT_TRUE(vf->RegularizeAndStep(Weights(), lrs, 42).ok());
  std::vector<float> p(s.L.total);
  ASSERT_TRUE(vf->ReadParams(p).ok());
  std::vector<float> moved(s.L.total), moved_dev(s.L.total);
  for (size_t i = 0; i < p.size(); ++i) {
    moved[i] = host_params[i] - s.params[i];
    moved_dev[i] = p[i] - s.params[i];
  }
  EXPECT_LT(RelError(moved, moved_dev), 1e-4);
}

TEST_F(VulkanFieldOptimizerTest, BadSizesAndStepsAreRefused) {
  const Case s = MakeCase(8, 3);
  auto vf = Make(s);
  ASSERT_NE(vf, nullptr);
  std::vector<float> short_array(s.L.total - 1);
  EXPECT_EQ(vf->ReadParams(short_array).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->SetAdamMoments(short_array, short_array).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->ReadAdamMoments(short_array, short_array).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->RegularizeAndStep(Weights(), FieldLrs{1e-3, 1e-3}, 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  std::vector<float> bad_means(5);
  EXPECT_EQ(vf->BackwardOnDevice(TestQuery(0), bad_means, {}, {}, {}).code(), absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace streetsim::field
