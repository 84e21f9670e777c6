// Gradient checks of the extended field (scene/field/extended): the double analytic backward
// against central differences of the double forward, every parameter group (planes, S3Gaussian's
// MLP, each module's parameters, the canonical Gaussians the field reads), and the float analytic
// gradients against the double ones; every module on, each module alone, all off. With every
// module off the extended field equals FieldForward (the strict ablation).
#include <cmath>
#include <cstdio>
#include <functional>
#include <random>
#include <string>

#include "gtest/gtest.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/field_eval.h"
#include "tests/field/ext_test_fields.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

using testing::All;
using testing::ArrayOf;
using testing::ExtGroup;
using testing::ExtInputsOf;
using testing::ExtModelOf;
using testing::ExtProblem;
using testing::ExtValues;
using testing::kExtOut;
using testing::MakeExtProblem;
using testing::RelDiff;
using testing::RelError;
using testing::SmallConfig;
using testing::TestAabb;

// L = Σ w · outputs + kl_weight · Σ KL.
double Loss(const ExtProblem& p, const ExtValues<double>& c, ThreadPool& pool, ExtWorkspace& ws) {
  std::vector<double> out[5];
  for (int o = 0; o < 5; ++o) out[o].assign(p.n * kExtOut[o], 0.0);
  ExtOutputs<double> eo{out[0].data(), out[1].data(), p.ec.decoder ? out[2].data() : nullptr,
                        p.ec.decoder ? out[3].data() : nullptr, p.ec.decoder ? out[4].data() : nullptr};
  absl::StatusOr<double> kl = ExtendedForward<double>(ExtModelOf(p, c), p.pass, ExtInputsOf(p, c), eo, pool, ws);
  EXPECT_TRUE(kl.ok()) << kl.status();
  double l = p.kl_weight * kl.value_or(0);
  for (int o = 0; o < 5; ++o)
    for (size_t i = 0; i < out[o].size(); ++i) l += p.v.w[o][i] * out[o][i];
  return l;
}

template <typename T>
struct Grads {
  std::vector<T> base, ext, means, opacity, scales, rotations;
};

template <typename T>
Grads<double> Analytic(const ExtProblem& p, ThreadPool& pool) {
  const ExtValues<T> c = testing::CastValues<T>(p.v);
  Grads<T> g;
  g.base.assign(p.BL.total, T(0));
  g.ext.assign(p.EL.total(), T(0));
  g.means.assign(p.n * 3, T(0));
  g.opacity.assign(p.n, T(0));
  g.scales.assign(p.n * 3, T(0));
  g.rotations.assign(p.n * 4, T(0));
  ExtWorkspace ws;
  ExtOutputGrads<T> d{c.w[0].data(), c.w[1].data(), c.w[2].data(), c.w[3].data(), c.w[4].data()};
  ExtInputGrads<T> gi{g.base.data(), g.ext.data(), g.means.data(), g.opacity.data(), g.scales.data(),
                      g.rotations.data()};
  absl::StatusOr<double> kl =
      ExtendedBackward<T>(ExtModelOf(p, c), p.pass, ExtInputsOf(p, c), d, p.kl_weight, gi, pool, ws);
  EXPECT_TRUE(kl.ok()) << kl.status();
  auto dv = [](const std::vector<T>& v) { return std::vector<double>(v.begin(), v.end()); };
  return {dv(g.base), dv(g.ext), dv(g.means), dv(g.opacity), dv(g.scales), dv(g.rotations)};
}

// Checks every group; prints a line per group. Returns the number of groups checked.
int CheckAll(ExtProblem& p, const char* tag) {
  ThreadPool serial(1), pool(2);
  ExtWorkspace ws;
  const Grads<double> ad = Analytic<double>(p, pool);
  const Grads<double> af = Analytic<float>(p, pool);
  const std::vector<ExtGroup> groups = testing::ExtGroups(p);
  for (const ExtGroup& g : groups) {
    std::vector<double>& x = ArrayOf(p.v, g.array);
    const std::vector<double>& gd = ArrayOf(ad, g.array);
    const std::vector<double>& gf = ArrayOf(af, g.array);
    int excluded = 0;
    const double e = RelError(x, g.idx, gd, [&] { return Loss(p, p.v, serial, ws); }, &excluded);
    const double ef = RelDiff(gf, gd, g.idx);
    std::printf("[%s] %-16s %5zu entries: double vs FD %.1e (%d excluded), float vs double %.1e\n", tag,
                g.name.c_str(), g.idx.size(), e, excluded, ef);
    EXPECT_LT(e, 1e-6) << tag << " " << g.name;
    EXPECT_LT(ef, 1e-4) << tag << " " << g.name;
    EXPECT_LE(excluded, static_cast<int>(g.idx.size() / 10)) << tag << " " << g.name;
    // A gradient that is identically zero would pass vacuously.
    double norm = 0;
    for (size_t i : g.idx) norm += std::abs(gd[i]);
    EXPECT_GT(norm, 0) << tag << " " << g.name << ": zero gradient";
  }
  return static_cast<int>(groups.size());
}

TEST(ExtendedFieldGradCheck, EveryModuleOn) {
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 10, 0.37, 1);
  EXPECT_EQ(CheckAll(p, "all on"), 13);  // planes x2, MLP, 6 module groups + gate, 4 canonical
}

TEST(ExtendedFieldGradCheck, EveryModuleOnNearTheLogEnd) {
  // t + Δ clamps to the axis end: that token holds the last state.
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 6, 0.85, 2);
  CheckAll(p, "all on, t 0.85");
}

TEST(ExtendedFieldGradCheck, EachModuleAlone) {
  for (const char* m : {"encoder", "vae", "temporal", "attention", "gru", "decoder"}) {
    ExtProblem p = MakeExtProblem(testing::OnlyModule(m), 6, -0.2, 3);
    CheckAll(p, m);
  }
}

TEST(ExtendedFieldGradCheck, InferenceUsesTheMean) {
  // z = μ: the pass is deterministic whatever the noise seed; training with ε differs.
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 6, 0.1, 4);
  ThreadPool pool(2);
  ExtWorkspace ws;
  p.pass.training = false;
  const double a = Loss(p, p.v, pool, ws);
  p.pass.noise_seed += 1;
  EXPECT_EQ(Loss(p, p.v, pool, ws), a);
  p.pass.training = true;
  const double b = Loss(p, p.v, pool, ws);
  EXPECT_NE(b, a);
  EXPECT_EQ(Loss(p, p.v, pool, ws), b);  // same seed, same ε
  CheckAll(p, "vae training seed 2");
  p.pass.training = false;
  CheckAll(p, "inference");
}

TEST(ExtendedFieldAblation, EveryModuleOffIsS3Gaussian) {
  for (double t : {-1.3, -0.6, 0.0, 0.37, 1.0}) {
    ExtProblem p = MakeExtProblem(ExtendedFieldConfig(), 40, t, 5);
    ASSERT_EQ(p.EL.total(), 0u);
    ThreadPool pool(2);
    ExtWorkspace ws;
    FieldWorkspace fws;
    std::vector<double> dx(p.n * 3), dsh(p.n * kShOutputs), ex(p.n * 3), esh(p.n * kShOutputs);
    FieldQuery q = testing::TestQuery(t);
    FieldForward<double>(p.BL, p.v.base.data(), q, p.v.means.data(), nullptr, p.n, dx.data(), dsh.data(), pool, fws);
    ExtOutputs<double> eo{ex.data(), esh.data()};
    ExtInputs<double> in{p.n, p.v.means.data()};
    ASSERT_TRUE(ExtendedForward<double>(ExtModelOf(p, p.v), p.pass, in, eo, pool, ws).ok());
    double worst = 0;
    for (size_t i = 0; i < dx.size(); ++i) worst = std::max(worst, std::abs(dx[i] - ex[i]));
    for (size_t i = 0; i < dsh.size(); ++i) worst = std::max(worst, std::abs(dsh[i] - esh[i]));
    EXPECT_LT(worst, 1e-12) << "t " << t;
    // And its backward is FieldBackward's.
    std::vector<double> gb(p.BL.total, 0.0), gm(p.n * 3, 0.0), fb(p.BL.total, 0.0), fm(p.n * 3, 0.0);
    FieldBackward<double>(p.BL, p.v.base.data(), q, p.v.means.data(), p.n, p.v.w[0].data(), p.v.w[1].data(),
                          fb.data(), fm.data(), pool, fws);
    ExtOutputGrads<double> d{p.v.w[0].data(), p.v.w[1].data()};
    ExtInputGrads<double> gi{gb.data(), nullptr, gm.data()};
    ASSERT_TRUE(ExtendedBackward<double>(ExtModelOf(p, p.v), p.pass, in, d, 0.0, gi, pool, ws).ok());
    EXPECT_LT(RelDiff(gb, fb, All(gb.size())), 1e-12) << "t " << t;
    EXPECT_LT(RelDiff(gm, fm, All(gm.size())), 1e-12) << "t " << t;
  }
}

TEST(ExtendedFieldAblation, ThreadCountsAgree) {
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 300, 0.2, 6);
  ThreadPool one(1), two(2);
  const Grads<double> a = Analytic<double>(p, one), b = Analytic<double>(p, two);
  EXPECT_EQ(a.base.size(), b.base.size());
  // Plane gradients are scattered in row order: identical; the MLP sums differ by rounding.
  for (const PlaneInfo& pi : p.BL.planes)
    for (size_t i = 0; i < pi.size(p.BL.channels); ++i) ASSERT_EQ(a.base[pi.offset + i], b.base[pi.offset + i]);
  EXPECT_LT(RelDiff(a.ext, b.ext, All(a.ext.size())), 1e-12);
  EXPECT_EQ(a.means, b.means);
  // The forward is per row: identical bits for any thread count and chunking (float).
  for (const char* modules : {"none", "all"}) {
    ExtendedFieldConfig c = *ExtendedFieldConfig::WithModules(modules);
    c.heads = 2, c.vae_latent = 3, c.gru_hidden = 3, c.window_k = 1, c.fourier_frequencies = 2;
    ExtProblem q = MakeExtProblem(c, 1000, 0.2, 8);
    const ExtValues<float>& f = q.f;
    std::vector<float> dx1(q.n * 3), dsh1(q.n * kShOutputs), dx2(q.n * 3), dsh2(q.n * kShOutputs);
    ExtWorkspace ws1, ws2;
    ASSERT_TRUE(
        ExtendedForward<float>(ExtModelOf(q, f), q.pass, ExtInputsOf(q, f), {dx1.data(), dsh1.data()}, one, ws1).ok());
    ASSERT_TRUE(
        ExtendedForward<float>(ExtModelOf(q, f), q.pass, ExtInputsOf(q, f), {dx2.data(), dsh2.data()}, two, ws2).ok());
    EXPECT_EQ(dx1, dx2) << modules;
    EXPECT_EQ(dsh1, dsh2) << modules;
  }
}

TEST(ExtendedFieldConfigTest, ModulesParseAndBadValuesAreErrors) {
  absl::StatusOr<ExtendedFieldConfig> c = ExtendedFieldConfig::WithModules("vae,gru");
  ASSERT_TRUE(c.ok());
  EXPECT_EQ(c->ModulesString(), "vae,gru");
  EXPECT_EQ(ExtendedFieldConfig::WithModules("all")->ModulesString(), "encoder,vae,temporal,attention,gru,decoder");
  EXPECT_EQ(ExtendedFieldConfig::WithModules("none")->ModulesString(), "none");
  EXPECT_FALSE(ExtendedFieldConfig::WithModules("vae,bogus").ok());
  EXPECT_FALSE(ExtendedFieldConfig::WithModules("").ok());
  ExtendedFieldConfig bad = ExtendedFieldConfig::AllOn();
  bad.heads = 3;  // width 8
  EXPECT_FALSE(ExtendedLayout::Make(SmallConfig(), bad).ok());
  bad = ExtendedFieldConfig::AllOn();
  bad.window_dt = -1;
  EXPECT_FALSE(ExtendedLayout::Make(SmallConfig(), bad).ok());
  // Spec sizes: model dim 64, 4 x 16 heads, K = 5.
  absl::StatusOr<ExtendedLayout> spec = ExtendedLayout::Make(FieldConfig(), *ExtendedFieldConfig::WithModules("all"));
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->tokens, 5);
  EXPECT_EQ(spec->token_dim, 16 + 128);
  EXPECT_EQ(spec->attention.heads, 4);
  EXPECT_EQ(spec->attention.head_dim(), 16);
}

// The VAE's dilated variance branch (vae_dilation > 0): gradients through the dilated taps
// (planes, means) and the two Linears, alone and with every module on.
ExtendedFieldConfig Dilated(ExtendedFieldConfig c, int d) {
  c.vae = true;
  c.vae_dilation = d;
  return c;
}

TEST(ExtendedFieldGradCheck, DilatedVarianceAlone) {
  for (int d : {1, 2}) {
    ExtendedFieldConfig c;
    c.vae_latent = 3;
    ExtProblem p = MakeExtProblem(Dilated(c, d), 8, -0.2, 20 + d);
    CheckAll(p, d == 1 ? "vae_dilated d 1" : "vae_dilated d 2");
  }
}

TEST(ExtendedFieldGradCheck, EveryModuleOnDilated) {
  ExtProblem p = MakeExtProblem(Dilated(ExtendedFieldConfig::AllOn(), 1), 10, 0.37, 22);
  EXPECT_EQ(CheckAll(p, "all on, vae_dilated"), 13);
  p.pass.training = false;
  CheckAll(p, "all on, vae_dilated, inference");
}

// Bilinear sample of a plane at continuous texel coordinates (a, b) with border clamp (grid_sample,
// align_corners), written out independently of hexplane_kernels.h.
double SampleAt(const std::vector<double>& params, const PlaneInfo& pi, int C, int k, double a, double b) {
  auto clampc = [](double v, int n) { return std::min(std::max(v, 0.0), static_cast<double>(n - 1)); };
  a = clampc(a, pi.width), b = clampc(b, pi.height);
  const int a0 = std::min(static_cast<int>(std::floor(a)), pi.width - 2);
  const int b0 = std::min(static_cast<int>(std::floor(b)), pi.height - 2);
  const double wa = a - a0, wb = b - b0;
  auto at = [&](int u, int v) { return params[pi.offset + (static_cast<size_t>(v) * pi.width + u) * C + k]; };
  return (1 - wa) * (1 - wb) * at(a0, b0) + wa * (1 - wb) * at(a0 + 1, b0) + (1 - wa) * wb * at(a0, b0 + 1) +
         wa * wb * at(a0 + 1, b0 + 1);
}

TEST(ExtendedFieldDilated, VarianceBranchIsTheDocumentedFormula) {
  // μ = 0 (Linear_mu zeroed), inference: Σ KL = ½ Σ (e^{lv} - lv - 1) with lv = Linear_var(S_dil),
  // S_dil computed here from the formula in extended_config.h.
  for (int d : {1, 3}) {
    ExtendedFieldConfig c;
    c.vae_latent = 3;
    ExtProblem p = MakeExtProblem(Dilated(c, d), 12, 0.1, 30 + d);
    p.pass.training = false;
    for (const nn::NnParamBlock& b : p.EL.params.blocks())
      if (b.name.rfind("vae.mu", 0) == 0)
        for (size_t i = 0; i < b.count; ++i) p.v.ext[b.offset + i] = 0;
    ThreadPool pool(2);
    ExtWorkspace ws;
    std::vector<double> dx(p.n * 3);
    absl::StatusOr<double> kl =
        ExtendedForward<double>(ExtModelOf(p, p.v), p.pass, ExtInputsOf(p, p.v), {dx.data()}, pool, ws);
    ASSERT_TRUE(kl.ok()) << kl.status();
    const FieldAabb a = TestAabb();
    const int C = p.BL.channels, D = p.BL.feature_dim(), lat = c.vae_latent;
    double expect = 0;
    for (size_t g = 0; g < p.n; ++g) {
      double px[3];
      std::vector<double> sdil(D);
      for (int l = 0; l < p.BL.num_levels; ++l) {
        const int R = p.BL.level_resolution[l];
        for (int k = 0; k < 3; ++k) {
          const double ext = a.max[k] - a.min[k];
          const double nrm = -2.0 / ext * p.v.means[g * 3 + k] + 1.0 + 2.0 * a.min[k] / ext;
          px[k] = (nrm + 1) / 2 * (R - 1);
        }
        for (int ch = 0; ch < C; ++ch) {
          double prod = 1;
          for (int plane : {0, 1, 3}) {  // xy, xz, yz
            const PlaneInfo& pi = p.BL.planes[l * kPlanesPerLevel + plane];
            const double u = px[kPlaneCoords[plane][0]], v = px[kPlaneCoords[plane][1]];
            prod *= 0.25 * (SampleAt(p.v.base, pi, C, ch, u + d, v) + SampleAt(p.v.base, pi, C, ch, u - d, v) +
                            SampleAt(p.v.base, pi, C, ch, u, v + d) + SampleAt(p.v.base, pi, C, ch, u, v - d));
          }
          sdil[l * C + ch] = prod;
        }
      }
      const double* w = p.v.ext.data() + p.EL.vae_var.w_offset;
      const double* bias = p.v.ext.data() + p.EL.vae_var.b_offset;
      for (int i = 0; i < lat; ++i) {
        double lv = bias[i];
        for (int j = 0; j < D; ++j) lv += w[i * D + j] * sdil[j];
        expect += 0.5 * (std::exp(lv) - lv - 1);
      }
    }
    EXPECT_GT(expect, 0);
    EXPECT_NEAR(*kl, expect, 1e-12 * expect) << "d " << d;
  }
}

TEST(ExtendedFieldDilated, ModulesAndLayout) {
  absl::StatusOr<ExtendedFieldConfig> c = ExtendedFieldConfig::WithModules("vae_dilated,gru");
  ASSERT_TRUE(c.ok());
  EXPECT_TRUE(c->vae);
  EXPECT_EQ(c->vae_dilation, 1);
  EXPECT_EQ(c->ModulesString(), "vae_dilated,gru");
  EXPECT_EQ(ExtendedFieldConfig::WithModules("all")->vae_dilation, 0);  // "all" keeps the plain VAE
  EXPECT_EQ(ExtendedFieldConfig::WithModules("all,vae_dilated")->ModulesString(),
            "encoder,vae_dilated,temporal,attention,gru,decoder");
  // The two Linears replace vae.in: M -> L on q and D -> L on S_dil.
  absl::StatusOr<ExtendedLayout> L = ExtendedLayout::Make(FieldConfig(), *c);
  ASSERT_TRUE(L.ok()) << L.status();
  EXPECT_EQ(L->vae_in.out, 0);
  EXPECT_EQ(L->vae_mu.in, 64);
  EXPECT_EQ(L->vae_mu.out, 32);
  EXPECT_EQ(L->vae_var.in, 128);
  EXPECT_EQ(L->vae_var.out, 32);
  ExtendedFieldConfig bad = *c;
  bad.vae_dilation = -1;
  EXPECT_FALSE(ExtendedLayout::Make(FieldConfig(), bad).ok());
  bad.vae_dilation = 17;
  EXPECT_FALSE(ExtendedLayout::Make(FieldConfig(), bad).ok());
}

TEST(ExtendedFieldDilated, DilationChangesOnlyTheVariance) {
  // Inference (z = μ): the outputs do not depend on the variance branch; training (ε) and the KL do.
  ExtendedFieldConfig c;
  c.vae_latent = 3;
  ExtProblem p = MakeExtProblem(Dilated(c, 1), 20, 0.3, 40);
  ThreadPool pool(2);
  ExtWorkspace ws;
  auto run = [&](bool training, std::vector<double>* dx) {
    p.pass.training = training;
    dx->assign(p.n * 3, 0.0);
    return *ExtendedForward<double>(ExtModelOf(p, p.v), p.pass, ExtInputsOf(p, p.v), {dx->data()}, pool, ws);
  };
  std::vector<double> a, b, ta, tb;
  const double kla = run(false, &a), tkla = run(true, &ta);
  for (const nn::NnParamBlock& blk : p.EL.params.blocks())
    if (blk.name.rfind("vae.var", 0) == 0)
      for (size_t i = 0; i < blk.count; ++i) p.v.ext[blk.offset + i] *= 0.5;
  const double klb = run(false, &b), tklb = run(true, &tb);
  EXPECT_EQ(a, b);
  EXPECT_NE(ta, tb);
  EXPECT_NE(kla, klb);
  EXPECT_EQ(kla, tkla);  // the KL does not depend on ε
  EXPECT_EQ(klb, tklb);
}

TEST(ExtendedFieldConfigTest, BadInputsAreErrors) {
  ExtProblem p = MakeExtProblem(ExtendedFieldConfig::AllOn(), 4, 0.0, 7);
  ThreadPool pool(1);
  ExtWorkspace ws;
  std::vector<double> dx(p.n * 3);
  ExtInputs<double> in{p.n, p.v.means.data()};  // the encoder needs opacity, scales, rotations
  EXPECT_FALSE(ExtendedForward<double>(ExtModelOf(p, p.v), p.pass, in, {dx.data()}, pool, ws).ok());
}

}  // namespace
}  // namespace streetsim::field
