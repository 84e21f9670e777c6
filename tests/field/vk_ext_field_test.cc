// The extended field on Vulkan (render/vulkan/field/ext/vulkan_extended_field.h) against the cpu
// double path (ExtendedForward<double> / ExtendedBackward<double>, which ext_grad_check_test checks
// against finite differences): forward outputs, Σ KL and every gradient group (planes, S3Gaussian's
// MLP, each module's parameters, canonical means / opacities / scales / rotations), each module
// alone and every module on, training (ε on) and inference passes — the Vulkan gradient check of
// each module. Also: several batches, the compare-and-swap scatter, bad positions stay in their
// rows, repeats give the same bits, parameter re-upload, errors, the VAE's dilated variance branch. Runs on the first GPU, else
// lavapipe; skips without a Vulkan device.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "render/common/thread_pool.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/extended/extended_field.h"
#include "render/vulkan/field/ext/vulkan_extended_field.h"
#include "tests/field/ext_test_fields.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::All;
using testing::ExtInputsOf;
using testing::ExtModelOf;
using testing::ExtProblem;
using testing::kExtOut;
using testing::MakeExtProblem;
using testing::OnlyModule;
using testing::RandomMeans;
using testing::RelDiff;
using testing::TestAabb;

const char* const kOutName[5] = {"dx", "dsh", "dscale", "drot", "dopacity"};

// Float32 tolerances: the Vulkan and cpu float paths sum in different orders (tiled GEMMs,
// per-chunk parameter-gradient partials, atomics); a float pass through ~20 ops whose sums have up to
// a few hundred terms stays well within 1e-5 of the double result on outputs (measured: see the
// printed worst) and 1e-4 on gradients (the cpu float path's own limit in ext_grad_check_test).
constexpr double kOutTol = 1e-5, kGradTol = 1e-4;

bool HaveVulkan() {
  static const bool have = !ListVulkanDevices().empty();
  return have;
}

// One pass's results on either side, in double.
struct Result {
  std::vector<double> out[5];
  double kl_fwd = 0, kl_bwd = 0;
  std::vector<double> base, ext, means, opacity, scales, rotations;
};

template <typename T>
std::vector<double> D(const std::vector<T>& v) {
  return std::vector<double>(v.begin(), v.end());
}

Result CpuDouble(const ExtProblem& p) {
  ThreadPool pool(2);
  ExtWorkspace ws;
  Result r;
  std::vector<double> out[5];
  for (int o = 0; o < 5; ++o) out[o].assign(p.n * kExtOut[o], 0.0);
  const bool dec = p.ec.decoder;
  ExtOutputs<double> eo{out[0].data(), out[1].data(), dec ? out[2].data() : nullptr, dec ? out[3].data() : nullptr,
                        dec ? out[4].data() : nullptr};
  absl::StatusOr<double> kl = ExtendedForward<double>(ExtModelOf(p, p.v), p.pass, ExtInputsOf(p, p.v), eo, pool, ws);
  EXPECT_TRUE(kl.ok()) << kl.status();
  r.kl_fwd = kl.value_or(0);
  for (int o = 0; o < 5; ++o) r.out[o] = out[o];
  r.base.assign(p.BL.total, 0), r.ext.assign(p.EL.total(), 0), r.means.assign(p.n * 3, 0);
  r.opacity.assign(p.n, 0), r.scales.assign(p.n * 3, 0), r.rotations.assign(p.n * 4, 0);
  ExtOutputGrads<double> dg{p.v.w[0].data(), p.v.w[1].data(), p.v.w[2].data(), p.v.w[3].data(), p.v.w[4].data()};
  ExtInputGrads<double> gi{r.base.data(),    r.ext.data(),    r.means.data(),
                           r.opacity.data(), r.scales.data(), r.rotations.data()};
  kl = ExtendedBackward<double>(ExtModelOf(p, p.v), p.pass, ExtInputsOf(p, p.v), dg, p.kl_weight, gi, pool, ws);
  EXPECT_TRUE(kl.ok()) << kl.status();
  r.kl_bwd = kl.value_or(0);
  return r;
}

VulkanFieldOptions SmallOptions(size_t batch = 65536, bool cas = false) {
  VulkanFieldOptions o;
  o.batch_rows = batch;
  o.force_cas_atomics = cas;
  o.max_plane_buffer_bytes = 2048;  // the small field's planes over all 4 plane buffers
  return o;
}

std::unique_ptr<VulkanExtendedField> MustCreate(const ExtProblem& p, const VulkanFieldOptions& o) {
  auto f = VulkanExtendedField::Create(ExtModelOf(p, p.f), o);
  EXPECT_TRUE(f.ok()) << f.status();
  if (!f.ok()) return nullptr;
  return *std::move(f);
}

// Forward then backward on the device. `prefill`: the gradient arrays start at this value (+= test).
Result RunVulkan(VulkanExtendedField& vf, const ExtProblem& p, float prefill = 0.f) {
  Result r;
  std::vector<float> out[5];
  for (int o = 0; o < 5; ++o) out[o].assign(p.n * kExtOut[o], std::numeric_limits<float>::quiet_NaN());
  const bool dec = p.ec.decoder;
  ExtOutputs<float> eo{out[0].data(), out[1].data(), dec ? out[2].data() : nullptr, dec ? out[3].data() : nullptr,
                       dec ? out[4].data() : nullptr};
  absl::StatusOr<double> kl = vf.Forward(p.pass, ExtInputsOf(p, p.f), eo);
  EXPECT_TRUE(kl.ok()) << kl.status();
  r.kl_fwd = kl.value_or(0);
  for (int o = 0; o < 5; ++o) r.out[o] = D(out[o]);
  std::vector<float> base(p.BL.total, prefill), ext(p.EL.total(), prefill), means(p.n * 3, prefill);
  std::vector<float> opacity(p.n, prefill), scales(p.n * 3, prefill), rotations(p.n * 4, prefill);
  ExtOutputGrads<float> dg{p.f.w[0].data(), p.f.w[1].data(), p.f.w[2].data(), p.f.w[3].data(), p.f.w[4].data()};
  ExtInputGrads<float> gi{base.data(), ext.data(), means.data(), opacity.data(), scales.data(), rotations.data()};
  kl = vf.Backward(p.pass, ExtInputsOf(p, p.f), dg, p.kl_weight, gi);
  EXPECT_TRUE(kl.ok()) << kl.status();
  r.kl_bwd = kl.value_or(0);
  auto less = [&](const std::vector<float>& v) {
    std::vector<double> x = D(v);
    for (double& e : x) e -= prefill;
    return x;
  };
  r.base = less(base), r.ext = less(ext), r.means = less(means);
  r.opacity = less(opacity), r.scales = less(scales), r.rotations = less(rotations);
  return r;
}

// Every output and gradient group of `vk` against the cpu double `ref`; prints one line per
// group, returns the worst relative error.
double Compare(const ExtProblem& p, const Result& vk, const Result& ref, const char* tag) {
  double worst = 0;
  auto check = [&](const std::string& name, const std::vector<double>& a, const std::vector<double>& b,
                   const std::vector<size_t>& idx, double tol) {
    const double e = RelDiff(a, b, idx);
    double norm = 0;
    for (size_t i : idx) norm += b[i] * b[i];
    std::printf("[%s] %-16s %5zu entries: vulkan vs cpu double %.1e\n", tag, name.c_str(), idx.size(), e);
    EXPECT_LT(e, tol) << tag << " " << name;
    EXPECT_GT(norm, 0) << tag << " " << name << ": a zero reference checks nothing";
    worst = std::max(worst, e);
  };
  for (int o = 0; o < 5; ++o) {
    if (o >= 2 && !p.ec.decoder) continue;
    check(kOutName[o], vk.out[o], ref.out[o], All(ref.out[o].size()), kOutTol);
  }
  if (p.ec.vae) {
    // σ² - log σ² - 1 cancels near σ² = 1 (small log-variances: measured 5.1e-6 with the dilated
    // branch), so the KL gets the gradients' tolerance.
    check("KL (forward)", {vk.kl_fwd}, {ref.kl_fwd}, {0}, kGradTol);
    check("KL (backward)", {vk.kl_bwd}, {ref.kl_bwd}, {0}, kGradTol);
  } else {
    EXPECT_EQ(vk.kl_fwd, 0.0);
    EXPECT_EQ(vk.kl_bwd, 0.0);
  }
  for (const testing::ExtGroup& g : testing::ExtGroups(p))
    check(g.name, testing::ArrayOf(vk, g.array), testing::ArrayOf(ref, g.array), g.idx, kGradTol);
  std::printf("[%s] worst %.1e\n", tag, worst);
  return worst;
}

class VulkanExtendedFieldTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!HaveVulkan()) GTEST_SKIP() << "no Vulkan device on this machine";
  }
};

// Each module alone and every module on, training and inference: the Vulkan gradient check.
TEST_F(VulkanExtendedFieldTest, EveryModuleMatchesTheCpuDoublePath) {
  for (const char* m : {"none", "encoder", "vae", "vae_dilated", "temporal", "attention", "gru", "decoder", "all",
                        "encoder,vae_dilated,temporal,attention,gru,decoder"}) {
    for (bool training : {true, false}) {
      ExtProblem p = MakeExtProblem(OnlyModule(m), 40, 0.37, 5);
      p.pass.training = training;
      auto vf = MustCreate(p, SmallOptions());
      ASSERT_NE(vf, nullptr);
      const std::string tag = std::string(m) + (training ? ", training" : ", inference");
      Compare(p, RunVulkan(*vf, p), CpuDouble(p), tag.c_str());
    }
  }
}

// Every module on near the log's end (token times clamp), spread over 3 batches, with the
// compare-and-swap scatter; gradients are added to what the arrays held.
TEST_F(VulkanExtendedFieldTest, BatchesCasAndAccumulation) {
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 40, 0.85, 9);
  const Result ref = CpuDouble(p);
  auto one = MustCreate(p, SmallOptions());
  auto three = MustCreate(p, SmallOptions(16, /*cas=*/true));
  ASSERT_TRUE(one && three);
  const Result a = RunVulkan(*one, p);
  const Result b = RunVulkan(*three, p, /*prefill=*/0.5f);
  EXPECT_EQ(three->last_backward().batches, 3);
  Compare(p, a, ref, "all, t 0.85, 1 batch");
  Compare(p, b, ref, "all, t 0.85, 3 batches, CAS, +=");
  // The forward is per row: the batch split changes no output bit.
  for (int o = 0; o < 5; ++o) EXPECT_EQ(a.out[o], b.out[o]) << kOutName[o];
  EXPECT_EQ(a.kl_fwd, b.kl_fwd);
}

// Same inputs, same bits: outputs, KL, MLP / extension / canonical gradients (the plane
// gradients come from float atomics, whose order varies: compared to rounding only).
TEST_F(VulkanExtendedFieldTest, RepeatsGiveTheSameBits) {
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 40, 0.1, 13);
  auto vf = MustCreate(p, SmallOptions(16));
  ASSERT_NE(vf, nullptr);
  const Result a = RunVulkan(*vf, p), b = RunVulkan(*vf, p);
  for (int o = 0; o < 5; ++o) EXPECT_EQ(a.out[o], b.out[o]);
  EXPECT_EQ(a.kl_fwd, b.kl_fwd);
  EXPECT_EQ(a.kl_bwd, b.kl_bwd);
  EXPECT_EQ(a.ext, b.ext);
  EXPECT_EQ(a.means, b.means);
  EXPECT_EQ(a.opacity, b.opacity);
  EXPECT_EQ(a.scales, b.scales);
  EXPECT_EQ(a.rotations, b.rotations);
  std::vector<size_t> mlp;
  for (size_t i = p.BL.grid_size; i < p.BL.total; ++i) mlp.push_back(i);
  for (size_t i : mlp) EXPECT_EQ(a.base[i], b.base[i]);
  EXPECT_LT(RelDiff(a.base, b.base, All(p.BL.grid_size)), 1e-6);
}

// NaN / inf positions: their rows' outputs are what the cpu gives (NaN where the cpu's are); no
// other row changes a bit; their gradients do not leak into the other rows' mean gradients.
TEST_F(VulkanExtendedFieldTest, BadPositionsStayInTheirRows) {
  ExtProblem clean = MakeExtProblem(ExtendedFieldConfig::AllOn(), 24, 0.2, 17);
  ExtProblem bad = clean;
  const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
  const std::vector<size_t> bad_rows = {2, 7, 11};
  bad.f.means[2 * 3] = nan, bad.f.means[7 * 3 + 1] = inf, bad.f.means[11 * 3 + 2] = -inf;
  for (size_t i = 0; i < bad.v.means.size(); ++i) bad.v.means[i] = bad.f.means[i];
  auto vf = MustCreate(clean, SmallOptions());
  ASSERT_NE(vf, nullptr);
  const Result a = RunVulkan(*vf, clean), b = RunVulkan(*vf, bad);
  const Result ref = CpuDouble(bad);
  for (int o = 0; o < 5; ++o) {
    for (size_t r = 0; r < bad.n; ++r) {
      const bool is_bad = std::find(bad_rows.begin(), bad_rows.end(), r) != bad_rows.end();
      for (int k = 0; k < kExtOut[o]; ++k) {
        const size_t i = r * kExtOut[o] + k;
        if (!is_bad) {
          EXPECT_EQ(a.out[o][i], b.out[o][i]) << kOutName[o] << " row " << r;
        } else {
          EXPECT_EQ(std::isnan(b.out[o][i]), std::isnan(ref.out[o][i])) << kOutName[o] << " row " << r;
        }
      }
    }
  }
  for (size_t r = 0; r < bad.n; ++r) {
    if (std::find(bad_rows.begin(), bad_rows.end(), r) != bad_rows.end()) continue;
    for (int k = 0; k < 3; ++k) EXPECT_TRUE(std::isfinite(b.means[r * 3 + k])) << "row " << r;
  }
}

// The spec's sizes (136 MiB of planes: 2 plane buffers on lavapipe; D 128, K 5, model dim 64, 4
// heads, VAE 32, GRU 32, m 8), every module on, 96 Gaussians in 3 batches, against the cpu float
// path (a double copy of the spec's planes would not add much here; the small cases above hold
// every module against double).
TEST_F(VulkanExtendedFieldTest, SpecSizesMatchCpuFloat) {
  const FieldConfig bc;  // spec sizes
  absl::StatusOr<DeformationField> base = DeformationField::Create(bc, TestAabb(), {0, 1000000}, 4);
  ASSERT_TRUE(base.ok()) << base.status();
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> u(-0.3f, 0.3f);
  for (const PlaneInfo& pi : base->layout().planes) {
    if (!PlaneHasTime(pi.plane)) continue;
    for (size_t i = 0; i < pi.size(bc.channels); ++i) base->mutable_params()[pi.offset + i] += u(rng);
  }
  absl::StatusOr<ExtendedFieldConfig> ec = ExtendedFieldConfig::WithModules("all");
  ASSERT_TRUE(ec.ok());
  ec->window_dt = 0.1;
  absl::StatusOr<ExtendedField> ef = ExtendedField::Create(*std::move(base), *ec, 6);
  ASSERT_TRUE(ef.ok()) << ef.status();
  for (float& x : ef->mutable_params()) x += u(rng);  // off the init (zero gate and decoder outputs)
  const size_t n = 96;
  const std::vector<double> md = RandomMeans<double>(n, n / 4, 8);
  std::vector<float> means(md.begin(), md.end()), opacity(n), scales(n * 3), rotations(n * 4), w[5];
  std::normal_distribution<float> g;
  for (float& x : opacity) x = g(rng);
  for (float& x : scales) x = -1.5f + u(rng) * 2;
  for (float& x : rotations) x = g(rng);
  for (int o = 0; o < 5; ++o) {
    w[o].resize(n * kExtOut[o]);
    for (float& x : w[o]) x = g(rng);
  }
  ExtPass pass;
  pass.time_coord = 0.3;
  pass.training = true;
  pass.noise_seed = 99;
  const ExtInputs<float> in{n, means.data(), opacity.data(), scales.data(), rotations.data()};
  const ExtOutputGrads<float> dg{w[0].data(), w[1].data(), w[2].data(), w[3].data(), w[4].data()};
  struct Side {
    std::vector<float> out[5], base, ext, means, opacity, scales, rotations;
    double kl = 0;
  } side[2];
  VulkanFieldOptions o;
  o.batch_rows = 32;
  absl::StatusOr<std::unique_ptr<VulkanExtendedField>> vf = VulkanExtendedField::Create(*ef, o);
  ASSERT_TRUE(vf.ok()) << vf.status();
  std::printf("spec sizes: %d plane buffer(s), batch %zu\n", (*vf)->plane_buffers(), (*vf)->batch_rows());
  ThreadPool pool(2);
  ExtWorkspace ws;
  for (int k = 0; k < 2; ++k) {
    Side& s = side[k];
    for (int oi = 0; oi < 5; ++oi) s.out[oi].assign(n * kExtOut[oi], 0.f);
    s.base.assign(ef->base().layout().total, 0.f), s.ext.assign(ef->layout().total(), 0.f);
    s.means.assign(n * 3, 0.f), s.opacity.assign(n, 0.f), s.scales.assign(n * 3, 0.f);
    s.rotations.assign(n * 4, 0.f);
    const ExtOutputs<float> eo{s.out[0].data(), s.out[1].data(), s.out[2].data(), s.out[3].data(), s.out[4].data()};
    const ExtInputGrads<float> gi{s.base.data(),    s.ext.data(),    s.means.data(),
                                  s.opacity.data(), s.scales.data(), s.rotations.data()};
    absl::StatusOr<double> kl = k == 0 ? ExtendedForward<float>(ModelOf(*ef), pass, in, eo, pool, ws)
                                       : (*vf)->Forward(pass, in, eo);
    ASSERT_TRUE(kl.ok()) << kl.status();
    s.kl = *kl;
    kl = k == 0 ? ExtendedBackward<float>(ModelOf(*ef), pass, in, dg, 0.3, gi, pool, ws)
                : (*vf)->Backward(pass, in, dg, 0.3, gi);
    ASSERT_TRUE(kl.ok()) << kl.status();
  }
  EXPECT_EQ((*vf)->last_backward().batches, 3);
  auto check = [&](const char* name, const std::vector<float>& a, const std::vector<float>& b, size_t from,
                   size_t to) {
    std::vector<size_t> idx;
    for (size_t i = from; i < to; ++i) idx.push_back(i);
    const double e = RelDiff(D(a), D(b), idx);
    std::printf("[spec sizes vs cpu float] %-16s %9zu entries: %.1e\n", name, idx.size(), e);
    EXPECT_LT(e, kGradTol) << name;
  };
  for (int oi = 0; oi < 5; ++oi) check(kOutName[oi], side[1].out[oi], side[0].out[oi], 0, side[0].out[oi].size());
  check("KL", {static_cast<float>(side[1].kl)}, {static_cast<float>(side[0].kl)}, 0, 1);
  const FieldLayout& BL = ef->base().layout();
  check("planes", side[1].base, side[0].base, 0, BL.grid_size);
  check("s3gaussian mlp", side[1].base, side[0].base, BL.grid_size, BL.total);
  check("extension", side[1].ext, side[0].ext, 0, side[0].ext.size());
  check("means", side[1].means, side[0].means, 0, n * 3);
  check("opacity logits", side[1].opacity, side[0].opacity, 0, n);
  check("log scales", side[1].scales, side[0].scales, 0, n * 3);
  check("rotations", side[1].rotations, side[0].rotations, 0, n * 4);
}

// UpdateParams re-uploads both arrays; bad sizes are errors.
TEST_F(VulkanExtendedFieldTest, UpdateParamsAndErrors) {
  ExtProblem p = MakeExtProblem(OnlyModule("temporal"), 20, -0.4, 21);
  ExtProblem q = MakeExtProblem(OnlyModule("temporal"), 20, -0.4, 22);  // other parameters, same inputs
  q.f.means = p.f.means, q.v.means = p.v.means;
  auto vf = MustCreate(p, SmallOptions());
  ASSERT_NE(vf, nullptr);
  ASSERT_TRUE(vf->UpdateParams(q.f.base, q.f.ext).ok());
  Compare(q, RunVulkan(*vf, q), CpuDouble(q), "after UpdateParams");
  EXPECT_EQ(vf->UpdateParams(std::vector<float>(3), q.f.ext).code(), absl::StatusCode::kInvalidArgument);
  // The encoder without its inputs.
  ExtProblem e = MakeExtProblem(OnlyModule("encoder"), 4, 0, 1);
  auto ve = MustCreate(e, SmallOptions());
  ASSERT_NE(ve, nullptr);
  std::vector<float> dx(12);
  ExtInputs<float> no_geometry{e.n, e.f.means.data(), nullptr, nullptr, nullptr};
  EXPECT_EQ(ve->Forward(e.pass, no_geometry, {dx.data()}).status().code(), absl::StatusCode::kInvalidArgument);
}

// The VAE's dilated variance branch at a dilation of 2 texels (taps clamp at the small planes'
// borders more often), every module on, 3 batches.
TEST_F(VulkanExtendedFieldTest, DilatedVarianceBranchAtTwoTexels) {
  ExtendedFieldConfig c = ExtendedFieldConfig::AllOn();
  c.vae_dilation = 2;
  ExtProblem p = MakeExtProblem(c, 40, -0.6, 31);
  auto vf = MustCreate(p, SmallOptions(16));
  ASSERT_NE(vf, nullptr);
  Compare(p, RunVulkan(*vf, p), CpuDouble(p), "all, dilation 2, 3 batches");
}

}  // namespace
}  // namespace streetsim::field
