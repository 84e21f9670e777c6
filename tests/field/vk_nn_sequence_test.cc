// The extended field's sequence kernels on Vulkan (LayerNorm on token slices, Fourier time tokens,
// the VAE sampler, the attention core, a GRU step) against the cpu ops of scene/field/nn, float
// and double, as vk_nn_kernels_test.cc does for Linear and the element-wise kernels. Skips
// without a Vulkan device. Tolerances: tests/field/vk_nn_test_support.h.
#include <cmath>
#include <cstdio>
#include <vector>

#include "gtest/gtest.h"
#include "tests/field/vk_nn_test_support.h"

namespace streetsim::field::vknn {
namespace {

// ---- LayerNorm ----

TEST_F(VkNnTest, LayerNormMatchesCpuOnTokenSlices) {
  const int B = 1100, T = 3, dim = 45, j = 1;  // 1100 rows: 2 gradient chunks
  nn::NnLayout layout;
  layout.Add("pad", 5);
  auto spec = nn::MakeLayerNorm(&layout, "ln", dim);
  ASSERT_TRUE(spec.ok());
  const nn::LayerNormSpec& s = *spec;
  const std::vector<float> p = RandomVec(layout.total(), 100, 0.5f);
  const std::vector<float> g0 = RandomVec(layout.total(), 101);
  const Mat<float> x = Random(B, T * dim, 102, 2.0f), dy = Random(B, T * dim, 103);
  const Mat<float> xj = x.middleCols(j * dim, dim), dyj = dy.middleCols(j * dim, dim);
  Mat<float> y_ref, dx_ref;
  nn::LayerNormCache<float> cache;
  ASSERT_TRUE(nn::LayerNormForward<float>(s, p.data(), xj, &y_ref, &cache).ok());
  std::vector<float> g_ref = g0;
  ASSERT_TRUE(nn::LayerNormBackward<float>(s, p.data(), cache, dyj, &dx_ref, g_ref.data()).ok());
  const std::vector<double> pd(p.begin(), p.end());
  std::vector<double> g_d(g0.begin(), g0.end());
  Mat<double> y_d, dx_d;
  nn::LayerNormCache<double> cache_d;
  ASSERT_TRUE(nn::LayerNormForward<double>(s, pd.data(), D(xj), &y_d, &cache_d).ok());
  ASSERT_TRUE(nn::LayerNormBackward<double>(s, pd.data(), cache_d, D(dyj), &dx_d, g_d.data()).ok());

  const vk::Buffer pb = dev_->Upload(p), gb = dev_->Upload(g0), xb = dev_->Upload(x), dyb = dev_->Upload(dy);
  const vk::Buffer yb = dev_->Zeros(B * T * dim), hb = dev_->Zeros(B * dim), rb = dev_->Zeros(B * 2),
                   dxb = dev_->Zeros(B * T * dim);
  auto tok = [&](const vk::Buffer& b) { return View{&b, uint32_t(j * dim), B, dim, T * dim}; };
  const View rstd{&rb, 1, B, 1, 2};  // every second float
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().LayerNorm(rec, s, pb, tok(xb), tok(yb), Dense(hb, B, dim), rstd);
                    rec.Barrier();
                    k().LayerNormGrad(rec, s, pb, Dense(hb, B, dim), rstd, tok(dyb), tok(dxb), gb);
                  })
                  .ok());
  const Mat<float> y = dev_->Download(yb, B, T * dim), dx = dev_->Download(dxb, B, T * dim);
  const Mat<float> xhat = dev_->Download(hb, B, dim);
  const std::vector<float> r2 = dev_->Download(rb, B * 2);
  Mat<float> r(B, 1);
  for (int i = 0; i < B; ++i) r(i, 0) = r2[2 * i + 1];
  const std::vector<float> g = dev_->Download(gb, g0.size());
  auto grp = [](const auto& v, size_t off, size_t n) {
    return Eigen::Map<const Eigen::Matrix<typename std::decay_t<decltype(v)>::value_type, 1, Eigen::Dynamic>>(
        v.data() + off, n);
  };
  const double e_y = RelError(y_ref, Mat<float>(y.middleCols(j * dim, dim))), e_h = RelError(cache.xhat, xhat),
               e_r = RelError(cache.rstd, r), e_dx = RelError(dx_ref, Mat<float>(dx.middleCols(j * dim, dim))),
               e_gain = RelError(grp(g_ref, s.gain_offset, dim), grp(g, s.gain_offset, dim)),
               e_bias = RelError(grp(g_ref, s.bias_offset, dim), grp(g, s.bias_offset, dim));
  std::printf(
      "layer norm: y %.2e (double %.2e), xhat %.2e, rstd %.2e, dx %.2e (double %.2e), dgain %.2e (double "
      "%.2e), dbias %.2e (double %.2e)\n",
      e_y, RelError(y_d, Mat<float>(y.middleCols(j * dim, dim))), e_h, e_r, e_dx,
      RelError(dx_d, Mat<float>(dx.middleCols(j * dim, dim))), e_gain,
      RelError(grp(g_d, s.gain_offset, dim), grp(g, s.gain_offset, dim)), e_bias,
      RelError(grp(g_d, s.bias_offset, dim), grp(g, s.bias_offset, dim)));
  for (double e : {e_y, e_h, e_r, e_dx, e_gain, e_bias}) EXPECT_LT(e, kTol);
  EXPECT_EQ(r2[0], 0.0f) << "rstd's stride respected";
  EXPECT_EQ(Mat<float>(y.middleCols(0, dim)), Mat<float>::Zero(B, dim)) << "other tokens untouched";
  EXPECT_EQ(grp(g, 0, 5), grp(g0, 0, 5)) << "gradients outside the block untouched";
}

// ---- Temporal tokens ----

TEST_F(VkNnTest, FourierTokensMatchCpu) {
  const int B = 77;
  auto spec = nn::MakeFourierTime(6, 5, 11);
  ASSERT_TRUE(spec.ok());
  const nn::FourierTimeSpec& s = *spec;
  const int T = s.tokens, F = s.feature_dim, Dt = s.token_dim();
  Mat<float> times(B, T);
  std::mt19937_64 rng(110);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  for (Eigen::Index i = 0; i < times.size(); ++i) times.data()[i] = u(rng);
  const Mat<float> feats = Random(B, T * F, 111), dtok = Random(B, T * Dt, 112);
  Mat<float> tok_ref, df_ref;
  nn::FourierTimeCache<float> cache;
  ASSERT_TRUE(nn::FourierTimeForward<float>(s, times, feats, &tok_ref, &cache).ok());
  ASSERT_TRUE(nn::FourierTimeBackward<float>(s, cache, dtok, nullptr, &df_ref).ok());
  Mat<double> tok_d;
  nn::FourierTimeCache<double> cache_d;
  ASSERT_TRUE(nn::FourierTimeForward<double>(s, D(times), D(feats), &tok_d, &cache_d).ok());
  const vk::Buffer tb = dev_->Upload(times), fb = dev_->Upload(feats), db = dev_->Upload(dtok);
  const vk::Buffer ob = dev_->Zeros(B * T * Dt), dfb = dev_->Zeros(B * T * F);
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().FourierTokens(rec, s, Dense(tb, B, T), Dense(fb, B, T * F), Dense(ob, B, T * Dt));
                    k().FourierTokensGrad(rec, s, Dense(db, B, T * Dt), Dense(dfb, B, T * F));
                  })
                  .ok());
  const Mat<float> tok = dev_->Download(ob, B, T * Dt), df = dev_->Download(dfb, B, T * F);
  std::printf("fourier tokens: %.2e (double %.2e), d_features %.2e\n", RelError(tok_ref, tok), RelError(tok_d, tok),
              RelError(df_ref, df));
  EXPECT_LT(RelError(tok_ref, tok), kTolTranscendental);
  EXPECT_LT(RelError(tok_d, tok), kTolTranscendental);
  EXPECT_EQ(df, df_ref) << "a copy";
}

// ---- VAE ----

TEST_F(VkNnTest, VaeMatchesCpu) {
  const int B = 77, L = 13;
  const float w = 0.37f;
  auto spec = nn::MakeVae(L);
  ASSERT_TRUE(spec.ok());
  const Mat<float> ml = Random(B, 2 * L, 120), eps = Random(B, L, 121), dz = Random(B, L, 122);
  for (bool sample : {true, false}) {
    Mat<float> z_ref, dml_ref;
    nn::VaeCache<float> cache;
    if (sample) {
      ASSERT_TRUE(nn::VaeSampleForward<float>(*spec, ml, eps, &z_ref, &cache).ok());
      ASSERT_TRUE(nn::VaeSampleBackward<float>(*spec, cache, dz, &dml_ref).ok());
    } else {
      ASSERT_TRUE(nn::VaeMean<float>(*spec, ml, &z_ref).ok());
      dml_ref = Mat<float>::Zero(B, 2 * L);
      dml_ref.leftCols(L) = dz;
    }
    Mat<float> kl_ref(B, 1);
    Mat<double> kl_d(B, 1);
    for (int r = 0; r < B; ++r) {
      ASSERT_TRUE(nn::VaeKl<float>(*spec, ml.row(r), 1.0f, &kl_ref(r, 0), nullptr).ok());
      ASSERT_TRUE(nn::VaeKl<double>(*spec, D(ml).row(r), 1.0, &kl_d(r, 0), nullptr).ok());
    }
    float unused = 0;
    ASSERT_TRUE(nn::VaeKl<float>(*spec, ml, w, &unused, &dml_ref).ok());
    const vk::Buffer mb = dev_->Upload(ml), eb = dev_->Upload(eps), dzb = dev_->Upload(dz);
    const vk::Buffer zb = dev_->Zeros(B * L), kb = dev_->Zeros(B), dmb = dev_->Zeros(B * 2 * L);
    const View ev = sample ? Dense(eb, B, L) : View{};
    ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                      k().VaeSample(rec, L, Dense(mb, B, 2 * L), ev, Dense(zb, B, L), Dense(kb, B, 1));
                      k().VaeSampleGrad(rec, L, Dense(mb, B, 2 * L), ev, Dense(dzb, B, L), w, Dense(dmb, B, 2 * L));
                    })
                    .ok());
    const Mat<float> z = dev_->Download(zb, B, L), kl = dev_->Download(kb, B, 1), dml = dev_->Download(dmb, B, 2 * L);
    std::printf("vae %s: z %.2e, kl %.2e (double %.2e), d_mu_logvar %.2e\n", sample ? "sample" : "mean",
                RelError(z_ref, z), RelError(kl_ref, kl), RelError(kl_d, kl), RelError(dml_ref, dml));
    EXPECT_LT(RelError(z_ref, z), kTolTranscendental);
    EXPECT_LT(RelError(kl_ref, kl), kTolTranscendental);
    EXPECT_LT(RelError(dml_ref, dml), kTolTranscendental);
  }
}

// ---- Attention core ----

// The core on the cpu float cache's Q, K, V (Q as a slice of a wider buffer), vs its A, O and the
// backward's dQ, dK, dV.
void CheckAttentionCore(Dev* dev_, int B, int T, int heads, int M, int token_dim) {
  NnKernels& k = *dev_->k;
  nn::NnLayout layout;
  auto spec = nn::MakeAttention(&layout, "attn", M, token_dim, T, heads, M);
  ASSERT_TRUE(spec.ok()) << spec.status();
  const nn::AttentionSpec& s = *spec;
  const int dh = s.head_dim();
  std::vector<float> p(layout.total());
  std::mt19937_64 rng(130);
  nn::InitAttention(s, rng, p.data());
  const Mat<float> q = Random(B, M, 131), x = Random(B, T * token_dim, 132), dy = Random(B, M, 133);
  Mat<float> y;
  nn::AttentionCache<float> c;
  ASSERT_TRUE(nn::AttentionForward<float>(s, p.data(), q, x, &y, &c).ok());
  Mat<float> dq_unused, dx_unused;
  std::vector<float> g(p.size(), 0.0f);
  ASSERT_TRUE(nn::AttentionBackward<float>(s, p.data(), c, dy, &dq_unused, &dx_unused, g.data()).ok());
  // Double: the same core on the float cache's Q, K, V, dO.
  const std::vector<double> pd(p.begin(), p.end());
  nn::AttentionCache<double> cd;
  Mat<double> yd, dqd, dxd;
  std::vector<double> gd(p.size(), 0.0);
  ASSERT_TRUE(nn::AttentionForward<double>(s, pd.data(), D(q), D(x), &yd, &cd).ok());
  ASSERT_TRUE(nn::AttentionBackward<double>(s, pd.data(), cd, D(dy), &dqd, &dxd, gd.data()).ok());

  // Q as a slice of a wider buffer, K and V dense.
  Mat<float> qwide = Mat<float>::Zero(B, M + 4);
  qwide.middleCols(2, M) = c.Q;
  const vk::Buffer qb = dev_->Upload(qwide), kb = dev_->Upload(c.K), vb = dev_->Upload(c.V), dob = dev_->Upload(c.dO);
  const vk::Buffer ab = dev_->Zeros(B * heads * T), ob = dev_->Zeros(B * M);
  const vk::Buffer dqb = dev_->Zeros(B * M), dkb = dev_->Zeros(B * T * M), dvb = dev_->Zeros(B * T * M);
  const View Q{&qb, 2, uint32_t(B), uint32_t(M), uint32_t(M + 4)};
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k.AttentionCore(rec, T, heads, dh, Q, Dense(kb, B * T, M), Dense(vb, B * T, M),
                                    Dense(ab, B, heads * T), Dense(ob, B, M));
                    rec.Barrier();
                    k.AttentionCoreGrad(rec, T, heads, dh, Q, Dense(kb, B * T, M), Dense(vb, B * T, M),
                                        Dense(ab, B, heads * T), Dense(dob, B, M), Dense(dqb, B, M),
                                        Dense(dkb, B * T, M), Dense(dvb, B * T, M));
                  })
                  .ok());
  const Mat<float> A = dev_->Download(ab, B, heads * T), O = dev_->Download(ob, B, M);
  const Mat<float> dQ = dev_->Download(dqb, B, M), dK = dev_->Download(dkb, B * T, M),
                   dV = dev_->Download(dvb, B * T, M);
  std::printf(
      "attention core (T %d, %d heads x %d): A %.2e (double %.2e), O %.2e (double %.2e), dQ %.2e (double %.2e), dK "
      "%.2e (double "
      "%.2e), dV %.2e (double %.2e)\n",
      T, heads, dh, RelError(c.A, A), RelError(cd.A, A), RelError(c.O, O), RelError(cd.O, O), RelError(c.dQ, dQ),
      RelError(cd.dQ, dQ), RelError(c.dK, dK), RelError(cd.dK, dK), RelError(c.dV, dV), RelError(cd.dV, dV));
  EXPECT_LT(RelError(c.A, A), kTolTranscendental);
  EXPECT_LT(RelError(c.O, O), kTolTranscendental);
  EXPECT_LT(RelError(c.dQ, dQ), kTolTranscendental);
  EXPECT_LT(RelError(c.dK, dK), kTolTranscendental);
  EXPECT_LT(RelError(c.dV, dV), kTolTranscendental);
}

TEST_F(VkNnTest, AttentionCoreMatchesCpuCache) { CheckAttentionCore(dev_, 77, 5, 3, 21, 13); }

// Near the kernel's loop budget (3 T (head_dim + 1) + head_dim = 47 585 of 60 000): lavapipe would
// silently cut the loops past 65 535 trips, so this shows the budget's count is right.
TEST_F(VkNnTest, AttentionCoreAtItsLoopBudget) {
  CheckAttentionCore(dev_, 2, 240, 1, 65, 3);
  // Past the budget: a clear error, not a silently truncated loop.
  const vk::Buffer b = dev_->Zeros(256 * 100 * 2);
  const absl::Status st = dev_->Run([&](vk::Recorder& rec) {
    k().AttentionCore(rec, 256, 1, 100, Dense(b, 1, 100), Dense(b, 256, 100), Dense(b, 256, 100), Dense(b, 1, 256),
                      Dense(b, 1, 100));
  });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
}

// ---- GRU step, composed with the W_hh Linear as a Bi-GRU step would ----

TEST_F(VkNnTest, GruStepMatchesCpu) {
  const int B = 1100, Din = 10, H = 19;
  nn::NnLayout layout;
  auto spec = nn::MakeGruCell(&layout, "gru", Din, H);
  ASSERT_TRUE(spec.ok());
  const nn::GruCellSpec& s = *spec;
  std::vector<float> p(layout.total());
  std::mt19937_64 rng(140);
  nn::InitGruCell(s, rng, p.data());
  const Mat<float> gi = Random(B, 3 * H, 141), h_prev = Random(B, H, 142, 0.8f), dh = Random(B, H, 143);
  nn::GruStepCache<float> c;
  Mat<float> h_ref;
  ASSERT_TRUE(nn::GruStepForward<float>(s, p.data(), gi, h_prev, &h_ref, &c).ok());
  const Mat<float> gh = c.dgh;  // the hidden gates, kept there until the backward
  Mat<float> dgi_ref(B, 3 * H), dhp_ref;
  std::vector<float> g_ref(p.size(), 0.0f);
  ASSERT_TRUE(nn::GruStepBackward<float>(s, p.data(), c, dh, dgi_ref, &dhp_ref, g_ref.data()).ok());
  const nn::LinearSpec whh{H, 3 * H, true, s.w_hh, s.b_hh};
  const vk::Buffer pb = dev_->Upload(p), gib = dev_->Upload(gi), hpb = dev_->Upload(h_prev), dhb = dev_->Upload(dh);
  const vk::Buffer ghb = dev_->Zeros(B * 3 * H), hb = dev_->Zeros(B * H), rznb = dev_->Zeros(B * 3 * H);
  const vk::Buffer dgib = dev_->Zeros(B * 3 * H), dghb = dev_->Zeros(B * 3 * H), dhpb = dev_->Zeros(B * H);
  const vk::Buffer gb = dev_->Zeros(p.size());
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().Linear(rec, whh, pb, Dense(hpb, B, H), Dense(ghb, B, 3 * H), false);
                    rec.Barrier();
                    k().GruStep(rec, H, Dense(gib, B, 3 * H), Dense(ghb, B, 3 * H), Dense(hpb, B, H), Dense(hb, B, H),
                                Dense(rznb, B, 3 * H));
                    rec.Barrier();
                    k().GruStepGrad(rec, H, Dense(ghb, B, 3 * H), Dense(rznb, B, 3 * H), Dense(hpb, B, H),
                                    Dense(dhb, B, H), Dense(dgib, B, 3 * H), Dense(dghb, B, 3 * H), Dense(dhpb, B, H));
                    rec.Barrier();
                    k().LinearInputGrad(rec, whh, pb, Dense(dghb, B, 3 * H), Dense(dhpb, B, H), true);
                    k().LinearParamGrad(rec, whh, Dense(hpb, B, H), Dense(dghb, B, 3 * H), gb);
                  })
                  .ok());
  Mat<float> rzn_ref(B, 3 * H);
  rzn_ref << c.r, c.z, c.n;
  const Mat<float> h = dev_->Download(hb, B, H), rzn = dev_->Download(rznb, B, 3 * H);
  const Mat<float> dgi = dev_->Download(dgib, B, 3 * H), dgh = dev_->Download(dghb, B, 3 * H);
  const Mat<float> dhp = dev_->Download(dhpb, B, H);
  const std::vector<float> g = dev_->Download(gb, p.size());
  const auto gv = nn::ConstMatMap<float>(g.data(), 1, g.size()),
             gv_ref = nn::ConstMatMap<float>(g_ref.data(), 1, g.size());
  std::printf("gru step: gh %.2e, h %.2e, rzn %.2e, dgi %.2e, dgh %.2e, dh_prev %.2e, d(W_hh, b_hh) %.2e\n",
              RelError(gh, dev_->Download(ghb, B, 3 * H)), RelError(h_ref, h), RelError(rzn_ref, rzn),
              RelError(dgi_ref, dgi), RelError(c.dgh, dgh), RelError(dhp_ref, dhp), RelError(gv_ref, gv));
  EXPECT_LT(RelError(h_ref, h), kTolTranscendental);
  EXPECT_LT(RelError(rzn_ref, rzn), kTolTranscendental);
  EXPECT_LT(RelError(dgi_ref, dgi), kTolTranscendental);
  EXPECT_LT(RelError(c.dgh, dgh), kTolTranscendental);
  EXPECT_LT(RelError(dhp_ref, dhp), kTolTranscendental);
  EXPECT_LT(RelError(gv_ref, gv), kTolTranscendental);
}

}  // namespace
}  // namespace streetsim::field::vknn
