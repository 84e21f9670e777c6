// The Vulkan field (render/vulkan/field/vulkan_field.h) against the cpu field: forward vs the cpu
// double forward, backward vs the cpu double backward (which field_grad_check_test checks against
// finite differences) per parameter group, a directional finite-difference check of the Vulkan
// gradient through the Vulkan forward itself, the spec's sizes vs the cpu float path, bad
// positions, bad sizes. Runs on the first GPU, else lavapipe; skips without any Vulkan device.
#include <cmath>
#include <cstdio>
#include <limits>
#include <ostream>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_eval.h"
#include "render/vulkan/field/vulkan_field.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::Group;
using testing::ParamGroups;
using testing::RandomMeans;
using testing::RandomParams;
using testing::SmallConfig;
using testing::TestQuery;

bool HaveVulkan() {
  static const bool have = !ListVulkanDevices().empty();
  return have;
}

template <typename A, typename B>
double RelError(const A& ref, const B& x, const std::vector<size_t>& index) {
  double num = 0, den = 0;
  for (size_t i : index) {
    const double d = double(ref[i]) - double(x[i]);
    num += d * d;
    den += double(ref[i]) * double(ref[i]);
  }
  return std::sqrt(num / std::max(den, 1e-300));
}
template <typename A, typename B>
double RelError(const A& ref, const B& x) {
  std::vector<size_t> all(ref.size());
  for (size_t i = 0; i < all.size(); ++i) all[i] = i;
  return RelError(ref, x, all);
}

// A small field whose float and double parameters are the same numbers, Gaussians (some outside
// the AABB) and output gradients.
struct Small {
  FieldLayout L;
  std::vector<float> pf, mf, gdx_f, gdsh_f;
  std::vector<double> pd, md, gdx_d, gdsh_d;
  size_t n = 0;
};
Small MakeSmall(size_t n, uint64_t seed) {
  Small s;
  const FieldConfig c = SmallConfig();
  s.L = FieldLayout::Make(c);
  s.n = n;
  for (double v : RandomParams<double>(c, s.L, seed)) s.pf.push_back(static_cast<float>(v));
  for (double v : RandomMeans<double>(n, n / 4, seed + 7)) s.mf.push_back(static_cast<float>(v));
  testing::RandomOutputGrads(n, seed + 3, &s.gdx_f, &s.gdsh_f);
  s.pd.assign(s.pf.begin(), s.pf.end());
  s.md.assign(s.mf.begin(), s.mf.end());
  s.gdx_d.assign(s.gdx_f.begin(), s.gdx_f.end());
  s.gdsh_d.assign(s.gdsh_f.begin(), s.gdsh_f.end());
  return s;
}

// Spread the small field's planes over all 4 plane buffers (as the spec's over 2 on lavapipe).
VulkanFieldOptions SmallOptions(bool cas, size_t batch = 65536) {
  VulkanFieldOptions o;
  o.force_cas_atomics = cas;
  o.batch_rows = batch;
  o.max_plane_buffer_bytes = 2048;
  return o;
}

std::unique_ptr<VulkanField> MustCreate(const FieldLayout& L, const std::vector<float>& p,
                                        const VulkanFieldOptions& o) {
  auto f = VulkanField::Create(L, p, o);
  EXPECT_TRUE(f.ok()) << f.status();
  if (!f.ok()) return nullptr;
  return *std::move(f);
}

class VulkanFieldTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device on this machine";
  }
  ThreadPool pool_{1};
  FieldWorkspace ws_;
};

TEST_F(VulkanFieldTest, SmallForwardMatchesCpuDouble) {
  const Small s = MakeSmall(80, 11);
  auto vf = MustCreate(s.L, s.pf, SmallOptions(false));
  ASSERT_NE(vf, nullptr);
  EXPECT_EQ(vf->plane_buffers(), 4);
  std::printf("%s\n", vf->device_description().c_str());
  for (double t : {0.37, -1.3, 1.0}) {  // inside, clamped below, on the last time sample
    const FieldQuery q = TestQuery(t);
    std::vector<double> dx_d(s.n * 3), dsh_d(s.n * kShOutputs);
    FieldForward<double>(s.L, s.pd.data(), q, s.md.data(), nullptr, s.n, dx_d.data(), dsh_d.data(), pool_, ws_);
    std::vector<float> dx, dsh;
    ASSERT_TRUE(vf->Forward(q, s.mf, &dx, &dsh).ok());
    const double e_dx = RelError(dx_d, dx), e_dsh = RelError(dsh_d, dsh);
    std::printf("t %.2f: dx rel err %.2e, dsh %.2e\n", t, e_dx, e_dsh);
    EXPECT_LT(e_dx, 1e-5);
    EXPECT_LT(e_dsh, 1e-5);
    std::vector<float> dx_only;
    ASSERT_TRUE(vf->Forward(q, s.mf, &dx_only, nullptr).ok());
    EXPECT_EQ(dx_only, dx);
  }
}

struct BackwardCase {
  bool cas;
  size_t batch;
  bool with_dx, with_dsh;
};

void PrintTo(const BackwardCase& c, std::ostream* os) {
  *os << (c.cas ? "cas" : "atomic") << " batch " << c.batch << (c.with_dx ? " dx" : "") << (c.with_dsh ? " dsh" : "");
}

class VulkanFieldBackward : public VulkanFieldTest, public ::testing::WithParamInterface<BackwardCase> {};

TEST_P(VulkanFieldBackward, MatchesCpuDouble) {
  const BackwardCase bc = GetParam();
  const Small s = MakeSmall(96, 21);
  auto vf = MustCreate(s.L, s.pf, SmallOptions(bc.cas, bc.batch));
  ASSERT_NE(vf, nullptr);
  if (!bc.cas) std::printf("float atomics: %s\n", vf->uses_float_atomics() ? "yes" : "no (CAS loop)");
  EXPECT_FALSE(bc.cas && vf->uses_float_atomics());
  const FieldQuery q = TestQuery(0.37);
  std::vector<double> gp_d(s.L.total, 0.0), gm_d(s.n * 3, 0.0);
  FieldBackward<double>(s.L, s.pd.data(), q, s.md.data(), s.n, bc.with_dx ? s.gdx_d.data() : nullptr,
                        bc.with_dsh ? s.gdsh_d.data() : nullptr, gp_d.data(), gm_d.data(), pool_, ws_);
  // Backward adds: start from a non-zero array to check it.
  std::vector<float> gp(s.L.total, 0.5f), gm(s.n * 3, -0.25f);
  ASSERT_TRUE(vf->Backward(q, s.mf, bc.with_dx ? std::span<const float>(s.gdx_f) : std::span<const float>(),
                           bc.with_dsh ? std::span<const float>(s.gdsh_f) : std::span<const float>(), gp, gm)
                  .ok());
  for (float& v : gp) v -= 0.5f;
  for (float& v : gm) v += 0.25f;
  for (const Group& g : ParamGroups(s.L)) {
    const double e = RelError(gp_d, gp, g.index);
    std::printf("%-15s rel err %.2e\n", g.name.c_str(), e);
    const bool unused_head = (g.name == "pos head" && !bc.with_dx) || (g.name == "sh head" && !bc.with_dsh);
    if (unused_head) {
      for (size_t i : g.index) EXPECT_EQ(gp[i], 0.0f) << g.name;
    } else {
      EXPECT_LT(e, 2e-5) << g.name;
    }
  }
  const double e_means = RelError(gm_d, gm);
  std::printf("%-15s rel err %.2e (batches %d)\n", "means", e_means, vf->last_backward().batches);
  EXPECT_LT(e_means, 2e-5);
}

INSTANTIATE_TEST_SUITE_P(Cases, VulkanFieldBackward,
                         ::testing::Values(BackwardCase{false, 65536, true, true}, BackwardCase{true, 65536, true, true},
                                           BackwardCase{false, 40, true, true},  // 3 batches
                                           BackwardCase{true, 40, true, false}, BackwardCase{false, 65536, false, true}),
                         [](const ::testing::TestParamInfo<BackwardCase>& info) {
                           const BackwardCase& c = info.param;
                           return std::string(c.cas ? "Cas" : "Atomic") + (c.batch < 1000 ? "Batched" : "") +
                                  (c.with_dx ? "Dx" : "") + (c.with_dsh ? "Dsh" : "");
                         });

// The Vulkan gradient against central differences of the Vulkan forward, one direction per group
// (along the group's gradient): independent of the cpu code. Float forward, so a loose bound.
TEST_F(VulkanFieldTest, DirectionalFiniteDifferences) {
  Small s = MakeSmall(64, 31);
  auto vf = MustCreate(s.L, s.pf, SmallOptions(false));
  ASSERT_NE(vf, nullptr);
  const FieldQuery q = TestQuery(0.21);
  auto loss = [&](const std::vector<float>& params, const std::vector<float>& means) {
    EXPECT_TRUE(vf->UpdateParams(params).ok());
    std::vector<float> dx, dsh;
    EXPECT_TRUE(vf->Forward(q, means, &dx, &dsh).ok());
    double l = 0;
    for (size_t i = 0; i < dx.size(); ++i) l += double(s.gdx_f[i]) * dx[i];
    for (size_t i = 0; i < dsh.size(); ++i) l += double(s.gdsh_f[i]) * dsh[i];
    return l;
  };
  std::vector<float> gp(s.L.total, 0.0f), gm(s.n * 3, 0.0f);
  ASSERT_TRUE(vf->Backward(q, s.mf, s.gdx_f, s.gdsh_f, gp, gm).ok());
  std::vector<Group> groups = ParamGroups(s.L);
  groups.push_back({"means", {}});
  for (const Group& g : groups) {
    const bool means = g.name == "means";
    const size_t size = means ? s.mf.size() : s.L.total;
    const std::vector<float>& grad = means ? gm : gp;
    // Along the group's own gradient (largest signal; a wrong gradient is not parallel to the
    // true one): the directional derivative must equal its norm.
    std::vector<double> dir(size, 0.0);
    if (means) {
      for (size_t i = 0; i < size; ++i) dir[i] = grad[i];
    } else {
      for (size_t i : g.index) dir[i] = grad[i];
    }
    double norm = 0;  // unit direction: the step is eps whatever the group's size
    for (double d : dir) norm += d * d;
    for (double& d : dir) d /= std::sqrt(norm);
    double analytic = 0;
    for (size_t i = 0; i < size; ++i) analytic += dir[i] * grad[i];
    // Small enough that few ReLU kinks / texel edges are crossed (the trunk: 1.7e-3 at 3e-4,
    // 1.8e-2 at 1e-2), large enough for the float forward's rounding (1e-4 relative at most).
    const double eps = 3e-4;
    auto shifted = [&](double sign) {
      std::vector<float> p = s.pf, m = s.mf;
      std::vector<float>& x = means ? m : p;
      for (size_t i = 0; i < size; ++i) x[i] = static_cast<float>(x[i] + sign * eps * dir[i]);
      return loss(p, m);
    };
    const double fd = (shifted(1) - shifted(-1)) / (2 * eps);
    const double rel = std::abs(fd - analytic) / std::max(std::abs(analytic), 1e-3);
    std::printf("%-15s analytic %+.6e fd %+.6e rel %.1e\n", g.name.c_str(), analytic, fd, rel);
    EXPECT_LT(rel, 1e-2) << g.name;
  }
}

// Spec sizes (136 MiB of planes: two plane buffers on lavapipe) with a few hundred Gaussians, vs
// the cpu float path.
TEST_F(VulkanFieldTest, SpecSizesMatchCpuFloat) {
  const FieldConfig c;
  FieldAabb aabb;
  for (int k = 0; k < 3; ++k) {
    aabb.min[k] = -40 + 10 * k;
    aabb.max[k] = 60 - 15 * k;
  }
  auto field = DeformationField::Create(c, aabb, {0, 10'000'000}, 3);
  ASSERT_TRUE(field.ok()) << field.status();
  const FieldLayout& L = field->layout();
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<float> u(-0.3f, 0.3f);
  for (const PlaneInfo& pi : L.planes) {  // time planes off 1: the output depends on time
    if (!PlaneHasTime(pi.plane)) continue;
    for (size_t i = 0; i < pi.size(L.channels); ++i) field->mutable_params()[pi.offset + i] += u(rng);
  }
  const size_t n = 300;
  std::vector<float> means(n * 3), gdx(n * 3), gdsh(n * kShOutputs);
  for (size_t i = 0; i < n; ++i) {
    for (int k = 0; k < 3; ++k) {
      std::uniform_real_distribution<float> uk(aabb.min[k] - 2, aabb.max[k] + 2);  // a few outside
      means[i * 3 + k] = uk(rng);
    }
  }
  std::normal_distribution<float> g;
  for (float& v : gdx) v = g(rng);
  for (float& v : gdsh) v = g(rng);
  VulkanFieldOptions o;
  o.batch_rows = 128;  // 3 batches
  auto vf = VulkanField::Create(*field, o);
  ASSERT_TRUE(vf.ok()) << vf.status();
  std::printf("%s, %d plane buffers\n", (*vf)->device_description().c_str(), (*vf)->plane_buffers());
  const FieldQuery q = field->Query(3'300'000);
  const float* P = field->params().data();

  std::vector<float> dx_c(n * 3), dsh_c(n * kShOutputs), dx, dsh;
  FieldForward<float>(L, P, q, means.data(), nullptr, n, dx_c.data(), dsh_c.data(), pool_, ws_);
  ASSERT_TRUE((*vf)->Forward(q, means, &dx, &dsh).ok());
  std::printf("forward: dx rel err %.2e, dsh %.2e\n", RelError(dx_c, dx), RelError(dsh_c, dsh));
  EXPECT_LT(RelError(dx_c, dx), 1e-4);
  EXPECT_LT(RelError(dsh_c, dsh), 1e-4);

  std::vector<float> gp_c(L.total, 0.0f), gm_c(n * 3, 0.0f);
  FieldBackward<float>(L, P, q, means.data(), n, gdx.data(), gdsh.data(), gp_c.data(), gm_c.data(), pool_, ws_);
  std::vector<float> gp(L.total, 0.0f), gm(n * 3, 0.0f);
  ASSERT_TRUE((*vf)->Backward(q, means, gdx, gdsh, gp, gm).ok());
  for (const Group& grp : ParamGroups(L)) {
    const double e = RelError(gp_c, gp, grp.index);
    std::printf("%-15s rel err %.2e\n", grp.name.c_str(), e);
    EXPECT_LT(e, 1e-4) << grp.name;
  }
  std::printf("%-15s rel err %.2e\n", "means", RelError(gm_c, gm));
  EXPECT_LT(RelError(gm_c, gm), 1e-4);
}

// NaN and infinite positions land on the border texels as on the cpu: never outside a plane.
TEST_F(VulkanFieldTest, BadPositionsStayInsidePlanes) {
  Small s = MakeSmall(12, 41);
  const float inf = std::numeric_limits<float>::infinity(), nan = std::numeric_limits<float>::quiet_NaN();
  const float bad[] = {nan, inf, -inf, 1e30f, -1e30f, nan};
  for (size_t i = 0; i < 6; ++i) {
    s.mf[i * 3 + i % 3] = bad[i];
    s.mf[i * 3 + (i + 1) % 3] = bad[5 - i];
  }
  auto vf = MustCreate(s.L, s.pf, SmallOptions(false));
  ASSERT_NE(vf, nullptr);
  const FieldQuery q = TestQuery(0.5);
  std::vector<float> dx_c(s.n * 3), dsh_c(s.n * kShOutputs), dx, dsh;
  FieldForward<float>(s.L, s.pf.data(), q, s.mf.data(), nullptr, s.n, dx_c.data(), dsh_c.data(), pool_, ws_);
  ASSERT_TRUE(vf->Forward(q, s.mf, &dx, &dsh).ok());
  for (float v : dx) EXPECT_TRUE(std::isfinite(v));
  for (float v : dsh) EXPECT_TRUE(std::isfinite(v));
  EXPECT_LT(RelError(dx_c, dx), 1e-5);
  EXPECT_LT(RelError(dsh_c, dsh), 1e-5);
  std::vector<float> gp(s.L.total, 0.0f), gm(s.n * 3, 0.0f);
  ASSERT_TRUE(vf->Backward(q, s.mf, s.gdx_f, s.gdsh_f, gp, gm).ok());
  for (float v : gp) ASSERT_TRUE(std::isfinite(v));
  for (float v : gm) ASSERT_TRUE(std::isfinite(v));
  // A NaN / infinite coordinate is clamped: no gradient flows to it.
  EXPECT_EQ(gm[0], 0.0f);
  EXPECT_EQ(gm[1], 0.0f);
}

TEST_F(VulkanFieldTest, BadSizesAreClearErrors) {
  const Small s = MakeSmall(10, 51);
  std::vector<float> short_params(s.pf.begin(), s.pf.end() - 1);
  auto bad = VulkanField::Create(s.L, short_params, SmallOptions(false));
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument) << bad.status();
  VulkanFieldOptions tiny = SmallOptions(false);
  tiny.max_plane_buffer_bytes = 300;  // smaller than a plane
  EXPECT_EQ(VulkanField::Create(s.L, s.pf, tiny).status().code(), absl::StatusCode::kFailedPrecondition);
  tiny.max_plane_buffer_bytes = 1100;  // every level-1 plane alone: more than 4 buffers
  EXPECT_EQ(VulkanField::Create(s.L, s.pf, tiny).status().code(), absl::StatusCode::kFailedPrecondition);

  auto vf = MustCreate(s.L, s.pf, SmallOptions(false));
  ASSERT_NE(vf, nullptr);
  const FieldQuery q = TestQuery(0.0);
  std::vector<float> dx, dsh;
  const std::vector<float> seven(7, 0.0f);
  EXPECT_EQ(vf->Forward(q, seven, &dx, &dsh).code(), absl::StatusCode::kInvalidArgument);
  FieldQuery flat = q;
  flat.aabb_max[1] = flat.aabb_min[1];
  EXPECT_EQ(vf->Forward(flat, s.mf, &dx, &dsh).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->UpdateParams(short_params).code(), absl::StatusCode::kInvalidArgument);
  std::vector<float> gp(s.L.total), gm(s.n * 3);
  std::vector<float> gp_short(s.L.total - 1), gm_short(s.n * 3 - 1), gdx_short(s.n * 3 - 3);
  EXPECT_EQ(vf->Backward(q, s.mf, gdx_short, s.gdsh_f, gp, gm).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->Backward(q, s.mf, s.gdx_f, gdx_short, gp, gm).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->Backward(q, s.mf, s.gdx_f, s.gdsh_f, gp_short, gm).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(vf->Backward(q, s.mf, s.gdx_f, s.gdsh_f, gp, gm_short).code(), absl::StatusCode::kInvalidArgument);
  // Still usable after the errors; empty input is fine.
  EXPECT_TRUE(vf->Forward(q, s.mf, &dx, &dsh).ok());
  EXPECT_TRUE(vf->Forward(q, {}, &dx, &dsh).ok());
  EXPECT_TRUE(dx.empty());
}

}  // namespace
}  // namespace streetsim::field
