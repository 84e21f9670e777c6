// The extended field's Vulkan kernels (render/vulkan/field/nn/vk_nn_kernels.h) against the cpu ops
// of scene/field/nn in float (and double, printed: the cpu double path is the reference that
// field_nn_test gradient-checks against finite differences, so the kernels' agreement with it is
// their gradient check): Linear, sums, activations and the gate here; LayerNorm, temporal tokens,
// VAE, attention and GRU in vk_nn_sequence_test.cc. Odd sizes (rows not multiples of 64, widths
// not multiples of 16), token-slice views (offset j*D, stride T*D), accumulate on / off, more than
// one gradient chunk; same inputs twice = same bits; a NaN row stays in its row; bad views and a
// too small Reserve fail the recorder with a clear status. Runs on the first Vulkan device
// (lavapipe here); skips without one. Tolerances: tests/field/vk_nn_test_support.h.
#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include "gtest/gtest.h"
#include "tests/field/vk_nn_test_support.h"

namespace streetsim::field::vknn {
namespace {

// ---- Linear ----

TEST_F(VkNnTest, LinearMatchesCpuDenseAndTokenSlices) {
  const int in = 37, out = 45, B = 77, T = 3;
  for (int bias_mode : {0, 1, 2}) {
    const nn::LinearSpec s = MakeSpec(in, out, bias_mode);
    const std::vector<float> p = RandomVec(ParamCount(s), 1 + bias_mode, 0.3f);
    const vk::Buffer params = dev_->Upload(p);
    // Dense x, y written then accumulated.
    const Mat<float> x = Random(B, in, 2);
    const Mat<float> y0 = Random(B, out, 3);
    Mat<float> ref;
    ASSERT_TRUE(nn::LinearApply<float>(s, p.data(), x, &ref).ok());
    Mat<double> ref_d;
    const std::vector<double> pd(p.begin(), p.end());
    ASSERT_TRUE(nn::LinearApply<double>(s, pd.data(), D(x), &ref_d).ok());
    const vk::Buffer xb = dev_->Upload(x), yb = dev_->Upload(y0);
    ASSERT_TRUE(
        dev_->Run([&](vk::Recorder& rec) { k().Linear(rec, s, params, Dense(xb, B, in), Dense(yb, B, out), false); })
            .ok());
    const Mat<float> y = dev_->Download(yb, B, out);
    std::printf("linear bias %d: rel err vs cpu float %.2e, vs double %.2e\n", bias_mode, RelError(ref, y),
                RelError(ref_d, y));
    EXPECT_LT(RelError(ref, y), kTol);
    ASSERT_TRUE(
        dev_->Run([&](vk::Recorder& rec) { k().Linear(rec, s, params, Dense(xb, B, in), Dense(yb, B, out), true); })
            .ok());
    const Mat<float> y2 = dev_->Download(yb, B, out);
    EXPECT_LT(RelError(Mat<float>(2 * ref), y2), kTol) << "accumulate";

    // Token slices: x token j of [B, T*in] into token j of [B, T*out] (after a 7-float offset).
    const Mat<float> tokens = Random(B, T * in, 4);
    const Mat<float> ytok0 = Random(B, T * out, 5);
    std::vector<float> ybuf(7 + ytok0.size());
    std::memcpy(ybuf.data() + 7, ytok0.data(), ytok0.size() * 4);
    const vk::Buffer tb = dev_->Upload(tokens), ytb = dev_->Upload(ybuf);
    ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                      for (int j = 0; j < T; ++j) {
                        k().Linear(rec, s, params, View{&tb, uint32_t(j * in), B, in, T * in},
                                   View{&ytb, uint32_t(7 + j * out), B, out, T * out}, j == 1);
                      }
                    })
                    .ok());
    const std::vector<float> yt = dev_->Download(ytb, ybuf.size());
    EXPECT_EQ(yt[3], ybuf[3]) << "the offset's floats are not touched";
    const Mat<float> ytm = nn::ConstMatMap<float>(yt.data() + 7, B, T * out);
    for (int j = 0; j < T; ++j) {
      Mat<float> r;
      ASSERT_TRUE(nn::LinearApply<float>(s, p.data(), tokens.middleCols(j * in, in), &r).ok());
      if (j == 1) r += ytok0.middleCols(j * out, out);
      const double e = RelError(r, Mat<float>(ytm.middleCols(j * out, out)));
      EXPECT_LT(e, kTol) << "token " << j;
    }
  }
}

TEST_F(VkNnTest, LinearGradsMatchCpu) {
  const int in = 37, out = 45, B = 1100;  // 2 gradient chunks
  for (int bias_mode : {0, 1, 2}) {
    const nn::LinearSpec s = MakeSpec(in, out, bias_mode);
    const std::vector<float> p = RandomVec(ParamCount(s), 10 + bias_mode, 0.3f);
    const std::vector<float> g0 = RandomVec(p.size(), 20 + bias_mode);  // the gradients are added
    const Mat<float> x = Random(B, in, 11), dy = Random(B, out, 12), dx0 = Random(B, in, 13);
    for (bool accumulate : {false, true}) {
      Mat<float> dx_ref = dx0;
      std::vector<float> g_ref = g0;
      ASSERT_TRUE(nn::LinearGrad<float>(s, p.data(), x, dy, &dx_ref, accumulate, g_ref.data()).ok());
      const std::vector<double> pd(p.begin(), p.end());
      std::vector<double> g_d(g0.begin(), g0.end());
      Mat<double> dx_d = D(dx0);
      ASSERT_TRUE(nn::LinearGrad<double>(s, pd.data(), D(x), D(dy), &dx_d, accumulate, g_d.data()).ok());
      const vk::Buffer params = dev_->Upload(p), grads = dev_->Upload(g0);
      const vk::Buffer xb = dev_->Upload(x), dyb = dev_->Upload(dy), dxb = dev_->Upload(dx0);
      ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                        k().LinearInputGrad(rec, s, params, Dense(dyb, B, out), Dense(dxb, B, in), accumulate);
                        k().LinearParamGrad(rec, s, Dense(xb, B, in), Dense(dyb, B, out), grads);
                      })
                      .ok());
      const Mat<float> dx = dev_->Download(dxb, B, in);
      const std::vector<float> g = dev_->Download(grads, g0.size());
      // Gradient groups: W, b, and the untouched rest.
      auto group = [](const std::vector<float>& v, size_t off, size_t n) {
        return Mat<float>(nn::ConstMatMap<float>(v.data() + off, 1, n));
      };
      auto group_d = [](const std::vector<double>& v, size_t off, size_t n) {
        return Mat<double>(nn::ConstMatMap<double>(v.data() + off, 1, n));
      };
      const size_t nw = size_t(in) * out;
      const double e_dx = RelError(dx_ref, dx), e_w = RelError(group(g_ref, s.w_offset, nw), group(g, s.w_offset, nw));
      std::printf("linear grads bias %d acc %d: dx %.2e (double %.2e), dW %.2e (double %.2e)", bias_mode, accumulate,
                  e_dx, RelError(dx_d, dx), e_w, RelError(group_d(g_d, s.w_offset, nw), group(g, s.w_offset, nw)));
      EXPECT_LT(e_dx, kTol);
      EXPECT_LT(e_w, kTol);
      if (s.bias) {
        const double e_b = RelError(group(g_ref, s.b_offset, out), group(g, s.b_offset, out));
        std::printf(", db %.2e (double %.2e)", e_b, RelError(group_d(g_d, s.b_offset, out), group(g, s.b_offset, out)));
        EXPECT_LT(e_b, kTol);
      }
      std::printf("\n");
      for (size_t i = 0; i < g.size(); ++i) {
        const bool in_w = i >= s.w_offset && i < s.w_offset + nw;
        const bool in_b = s.bias && i >= s.b_offset && i < s.b_offset + out;
        if (!in_w && !in_b) {
          ASSERT_EQ(g[i], g0[i]) << "gradient " << i << " outside the layer's blocks changed";
        }
      }
    }
  }
}

TEST_F(VkNnTest, LinearGradOnTokenSlices) {
  const int in = 19, out = 23, B = 130, T = 3, j = 2;
  const nn::LinearSpec s = MakeSpec(in, out, 1);
  const std::vector<float> p = RandomVec(ParamCount(s), 30, 0.3f);
  const Mat<float> x = Random(B, T * in, 31), dy = Random(B, T * out, 32), dx0 = Random(B, T * in, 33);
  Mat<float> dx_ref = dx0.middleCols(j * in, in);
  std::vector<float> g_ref(p.size(), 0.0f);
  ASSERT_TRUE(nn::LinearGrad<float>(s, p.data(), x.middleCols(j * in, in), dy.middleCols(j * out, out), &dx_ref, true,
                                    g_ref.data())
                  .ok());
  const vk::Buffer params = dev_->Upload(p), grads = dev_->Zeros(p.size());
  const vk::Buffer xb = dev_->Upload(x), dyb = dev_->Upload(dy), dxb = dev_->Upload(dx0);
  const View xv{&xb, uint32_t(j * in), B, in, T * in}, dyv{&dyb, uint32_t(j * out), B, out, T * out};
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().LinearInputGrad(rec, s, params, dyv, View{&dxb, uint32_t(j * in), B, in, T * in}, true);
                    k().LinearParamGrad(rec, s, xv, dyv, grads);
                  })
                  .ok());
  const Mat<float> dx = dev_->Download(dxb, B, T * in);
  EXPECT_LT(RelError(dx_ref, Mat<float>(dx.middleCols(j * in, in))), kTol);
  EXPECT_EQ(Mat<float>(dx.middleCols(0, in)), Mat<float>(dx0.middleCols(0, in))) << "other tokens untouched";
  const std::vector<float> g = dev_->Download(grads, p.size());
  EXPECT_LT(RelError(nn::ConstMatMap<float>(g_ref.data(), 1, g.size()), nn::ConstMatMap<float>(g.data(), 1, g.size())),
            kTol);
}

TEST_F(VkNnTest, AddAndColumnSums) {
  const int B = 1100, C = 70;
  const Mat<float> x = Random(B, 2 * C, 40), y0 = Random(B, C, 41);
  const std::vector<float> g0 = RandomVec(C + 9, 42);
  const vk::Buffer xb = dev_->Upload(x), yb = dev_->Upload(y0), gb = dev_->Upload(g0);
  const View xv{&xb, uint32_t(C), B, C, 2 * C};  // the second half of each row
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().Add(rec, xv, Dense(yb, B, C));
                    k().ColumnSums(rec, xv, gb, 4);
                  })
                  .ok());
  const Mat<float> y = dev_->Download(yb, B, C);
  EXPECT_EQ(y, Mat<float>(y0 + x.middleCols(C, C))) << "one rounding per element: exact";
  const std::vector<float> g = dev_->Download(gb, g0.size());
  std::vector<float> ref = g0;
  nn::AddColumnSums(x.middleCols(C, C), ref.data() + 4);
  EXPECT_LT(RelError(nn::ConstMatMap<float>(ref.data(), 1, ref.size()), nn::ConstMatMap<float>(g.data(), 1, g.size())),
            kTol);
  for (int i : {0, 1, 2, 3, C + 4, C + 8}) EXPECT_EQ(g[i], g0[i]);
}

// ---- Determinism, NaN, errors ----

TEST_F(VkNnTest, SameInputsSameBits) {
  const int in = 40, out = 33, B = 1500;
  const nn::LinearSpec s = MakeSpec(in, out, 1);
  const std::vector<float> p = RandomVec(ParamCount(s), 50, 0.3f);
  const Mat<float> x = Random(B, in, 51), dy = Random(B, out, 52);
  std::vector<float> first;
  for (int run = 0; run < 2; ++run) {
    const vk::Buffer params = dev_->Upload(p), grads = dev_->Zeros(p.size());
    const vk::Buffer xb = dev_->Upload(x), dyb = dev_->Upload(dy);
    // A LayerNorm of width `out` over the parameters' first floats (gain at 0, bias at out), a gate at 1.
    const nn::LayerNormSpec ln{out, 1e-5, 0, size_t(out)};
    const vk::Buffer dxb = dev_->Zeros(B * out), rb = dev_->Upload(Random(B, 1, 53));
    ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                      k().LinearParamGrad(rec, s, Dense(xb, B, in), Dense(dyb, B, out), grads);
                      k().ColumnSums(rec, Dense(dyb, B, out), grads, 0);
                      k().LayerNormGrad(rec, ln, params, Dense(dyb, B, out), Dense(rb, B, 1), Dense(dyb, B, out),
                                        Dense(dxb, B, out), grads);
                      k().GateGrad(rec, params, 1, Dense(dyb, B, out), Dense(dyb, B, out), Dense(dxb, B, out), grads);
                    })
                    .ok());
    const std::vector<float> g = dev_->Download(grads, p.size());
    if (run == 0) {
      first = g;
    } else {
      EXPECT_EQ(0, std::memcmp(first.data(), g.data(), g.size() * 4)) << "bits differ between two runs";
    }
  }
}

TEST_F(VkNnTest, NanRowStaysInItsRow) {
  const int in = 21, out = 35, B = 90, bad = 70;
  const nn::LinearSpec s = MakeSpec(in, out, 1);
  const std::vector<float> p = RandomVec(ParamCount(s), 60, 0.3f);
  Mat<float> x = Random(B, in, 61), dy = Random(B, out, 62);
  x(bad, 3) = std::numeric_limits<float>::quiet_NaN();
  dy(bad, 5) = std::numeric_limits<float>::quiet_NaN();
  const vk::Buffer params = dev_->Upload(p), xb = dev_->Upload(x), dyb = dev_->Upload(dy);
  const vk::Buffer yb = dev_->Zeros(B * out), dxb = dev_->Zeros(B * in), ab = dev_->Zeros(B * in);
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().Linear(rec, s, params, Dense(xb, B, in), Dense(yb, B, out), false);
                    k().LinearInputGrad(rec, s, params, Dense(dyb, B, out), Dense(dxb, B, in), false);
                    k().Activation(rec, nn::Activation::kGelu, Dense(xb, B, in), Dense(ab, B, in));
                  })
                  .ok());
  const Mat<float> y = dev_->Download(yb, B, out), dx = dev_->Download(dxb, B, in), a = dev_->Download(ab, B, in);
  for (const Mat<float>* m : {&y, &dx, &a}) {
    for (Eigen::Index r = 0; r < m->rows(); ++r) {
      const bool finite = m->row(r).array().isFinite().all();
      EXPECT_EQ(finite, r != bad) << "row " << r;
    }
  }
}

// Rows r of m (row r of a Gaussian, or rows r*per .. r*per+per-1 of a token matrix) are finite
// exactly when r != bad.
void ExpectNanOnlyIn(const Mat<float>& m, int bad, int per, const char* what) {
  for (Eigen::Index r = 0; r < m.rows(); ++r) {
    EXPECT_EQ(m.row(r).array().isFinite().all(), r / per != bad) << what << " row " << r;
  }
}

TEST_F(VkNnTest, NanRowStaysInItsRowInEveryKernel) {
  const int B = 70, bad = 66, T = 3, heads = 2, dh = 5, M = heads * dh, L = 4, H = 6;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  nn::NnLayout layout;
  auto ln = nn::MakeLayerNorm(&layout, "ln", M);
  ASSERT_TRUE(ln.ok());
  std::vector<float> p = RandomVec(layout.total(), 150);
  Mat<float> x = Random(B, M, 151), dy = Random(B, M, 152), K = Random(B * T, M, 153), V = Random(B * T, M, 154);
  Mat<float> ml = Random(B, 2 * L, 155), gi = Random(B, 3 * H, 156), times = Random(B, T, 157);
  x(bad, 1) = nan;
  dy(bad, 2) = nan;
  K(bad * T + 1, 3) = nan;
  ml(bad, 1) = nan;  // a mu: z = mu without eps
  gi(bad, 2 * H + 1) = nan;
  times(bad, 2) = nan;
  auto fspec = nn::MakeFourierTime(3, T, 2);
  ASSERT_TRUE(fspec.ok());
  const int Dt = fspec->token_dim();
  const Mat<float> feats = Random(B, T * 2, 158);
  const vk::Buffer pb = dev_->Upload(p), gb = dev_->Zeros(p.size()), xb = dev_->Upload(x), dyb = dev_->Upload(dy);
  const vk::Buffer yb = dev_->Zeros(B * M), hb = dev_->Zeros(B * M), rb = dev_->Zeros(B), dxb = dev_->Zeros(B * M);
  const vk::Buffer kb = dev_->Upload(K), vb = dev_->Upload(V), ab = dev_->Zeros(B * heads * T), ob = dev_->Zeros(B * M);
  const vk::Buffer dqb = dev_->Zeros(B * M), dkb = dev_->Zeros(B * T * M), dvb = dev_->Zeros(B * T * M);
  const vk::Buffer mb = dev_->Upload(ml), zb = dev_->Zeros(B * L), klb = dev_->Zeros(B), dmb = dev_->Zeros(B * 2 * L);
  const vk::Buffer gib = dev_->Upload(gi), ghb = dev_->Upload(Random(B, 3 * H, 159)),
                   hpb = dev_->Upload(Random(B, H, 160));
  const vk::Buffer hgb = dev_->Zeros(B * H), rznb = dev_->Zeros(B * 3 * H), tb = dev_->Upload(times);
  const vk::Buffer fb = dev_->Upload(feats), tokb = dev_->Zeros(B * T * Dt);
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().LayerNorm(rec, *ln, pb, Dense(xb, B, M), Dense(yb, B, M), Dense(hb, B, M), Dense(rb, B, 1));
                    k().AttentionCore(rec, T, heads, dh, Dense(xb, B, M), Dense(kb, B * T, M), Dense(vb, B * T, M),
                                      Dense(ab, B, heads * T), Dense(ob, B, M));
                    k().VaeSample(rec, L, Dense(mb, B, 2 * L), View{}, Dense(zb, B, L), Dense(klb, B, 1));
                    k().VaeSampleGrad(rec, L, Dense(mb, B, 2 * L), View{}, Dense(zb, B, L), 0.5f, Dense(dmb, B, 2 * L));
                    k().GruStep(rec, H, Dense(gib, B, 3 * H), Dense(ghb, B, 3 * H), Dense(hpb, B, H), Dense(hgb, B, H),
                                Dense(rznb, B, 3 * H));
                    k().FourierTokens(rec, *fspec, Dense(tb, B, T), Dense(fb, B, T * 2), Dense(tokb, B, T * Dt));
                    rec.Barrier();
                    k().LayerNormGrad(rec, *ln, pb, Dense(hb, B, M), Dense(rb, B, 1), Dense(dyb, B, M),
                                      Dense(dxb, B, M), gb);
                    k().AttentionCoreGrad(rec, T, heads, dh, Dense(xb, B, M), Dense(kb, B * T, M), Dense(vb, B * T, M),
                                          Dense(ab, B, heads * T), Dense(dyb, B, M), Dense(dqb, B, M),
                                          Dense(dkb, B * T, M), Dense(dvb, B * T, M));
                  })
                  .ok());
  ExpectNanOnlyIn(dev_->Download(yb, B, M), bad, 1, "layer norm y");
  ExpectNanOnlyIn(dev_->Download(rb, B, 1), bad, 1, "layer norm rstd");
  ExpectNanOnlyIn(dev_->Download(dxb, B, M), bad, 1, "layer norm dx");
  ExpectNanOnlyIn(dev_->Download(ab, B, heads * T), bad, 1, "attention A");
  ExpectNanOnlyIn(dev_->Download(ob, B, M), bad, 1, "attention O");
  ExpectNanOnlyIn(dev_->Download(dqb, B, M), bad, 1, "attention dQ");
  ExpectNanOnlyIn(dev_->Download(dkb, B * T, M), bad, T, "attention dK");
  ExpectNanOnlyIn(dev_->Download(dvb, B * T, M), bad, T, "attention dV");
  ExpectNanOnlyIn(dev_->Download(zb, B, L), bad, 1, "vae z");
  ExpectNanOnlyIn(dev_->Download(klb, B, 1), bad, 1, "vae kl");
  ExpectNanOnlyIn(dev_->Download(dmb, B, 2 * L), bad, 1, "vae d_mu_logvar");
  ExpectNanOnlyIn(dev_->Download(hgb, B, H), bad, 1, "gru h");
  ExpectNanOnlyIn(dev_->Download(tokb, B, T * Dt), bad, 1, "fourier tokens");
}

TEST_F(VkNnTest, BadViewsAndSmallReserveFailTheRecorder) {
  const nn::LinearSpec s = MakeSpec(8, 8, 1);
  const std::vector<float> p = RandomVec(ParamCount(s), 70);
  const vk::Buffer params = dev_->Upload(p), xb = dev_->Zeros(100 * 8), yb = dev_->Zeros(100 * 8);
  // Past the buffer's end.
  absl::Status st =
      dev_->Run([&](vk::Recorder& rec) { k().Linear(rec, s, params, Dense(xb, 101, 8), Dense(yb, 101, 8), false); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  EXPECT_NE(st.message().find("past its buffer"), std::string::npos) << st;
  // Wrong width, stride < cols, indices past 2^32.
  st = dev_->Run([&](vk::Recorder& rec) { k().Linear(rec, s, params, Dense(xb, 10, 7), Dense(yb, 10, 8), false); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  st = dev_->Run([&](vk::Recorder& rec) { k().Add(rec, View{&xb, 0, 10, 8, 4}, Dense(yb, 10, 8)); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  st = dev_->Run([&](vk::Recorder& rec) { k().Add(rec, View{&xb, 0, 1u << 20, 8, 1u << 13}, Dense(yb, 10, 8)); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  // Parameters outside their buffer.
  const vk::Buffer small = dev_->Zeros(10);
  st = dev_->Run([&](vk::Recorder& rec) { k().Linear(rec, s, small, Dense(xb, 10, 8), Dense(yb, 10, 8), false); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  // A fresh kernel set with a small Reserve: more rows than reserved fail, the first error sticks.
  auto fresh = NnKernels::Create(*dev_->ctx);
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  ASSERT_TRUE((*fresh)->Reserve(50, 200).ok());
  const vk::Buffer grads = dev_->Zeros(p.size());
  st = dev_->Run([&](vk::Recorder& rec) {
    (*fresh)->LinearParamGrad(rec, s, Dense(xb, 100, 8), Dense(yb, 100, 8), grads);
    (*fresh)->ColumnSums(rec, Dense(xb, 10, 8), grads, 0);
  });
  EXPECT_EQ(st.code(), absl::StatusCode::kFailedPrecondition) << st;
  EXPECT_NE(st.message().find("Reserve"), std::string::npos) << st;
  st = dev_->Run([&](vk::Recorder& rec) { (*fresh)->ColumnSums(rec, Dense(xb, 10, 8), grads, 0); });
  EXPECT_TRUE(st.ok()) << st;
  // Without any Reserve.
  auto bare = NnKernels::Create(*dev_->ctx);
  ASSERT_TRUE(bare.ok());
  st = dev_->Run([&](vk::Recorder& rec) { (*bare)->ColumnSums(rec, Dense(xb, 10, 8), grads, 0); });
  EXPECT_EQ(st.code(), absl::StatusCode::kFailedPrecondition) << st;
  // A Reserve past the device's limits is refused.
  EXPECT_FALSE((*bare)->Reserve(1u << 31, 1u << 20).ok());
}

// ---- Activation and gate ----

TEST_F(VkNnTest, ActivationsMatchCpu) {
  const int B = 83, C = 29;
  Mat<float> x = Random(B, C, 80, 3.0f);
  x(0, 0) = -5.0f;  // GELU's tail: 1 + erf needs a relative accuracy (float cpu: 10% off)
  x(0, 1) = 40.0f;
  x(0, 2) = -90.0f;
  const Mat<float> dy = Random(B, C, 81);
  for (nn::Activation a : {nn::Activation::kRelu, nn::Activation::kGelu, nn::Activation::kSilu}) {
    Mat<float> y_ref, dx_ref;
    nn::ActivationCache<float> cache;
    nn::ActivationForward<float>(a, x, &y_ref, &cache);
    ASSERT_TRUE(nn::ActivationBackward<float>(a, cache, dy, &dx_ref).ok());
    Mat<double> y_d, dx_d;
    nn::ActivationCache<double> cache_d;
    nn::ActivationForward<double>(a, D(x), &y_d, &cache_d);
    ASSERT_TRUE(nn::ActivationBackward<double>(a, cache_d, D(dy), &dx_d).ok());
    const vk::Buffer xb = dev_->Upload(x), dyb = dev_->Upload(dy), yb = dev_->Zeros(B * C), dxb = dev_->Upload(dy);
    ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                      k().Activation(rec, a, Dense(xb, B, C), Dense(yb, B, C));
                      k().ActivationGrad(rec, a, Dense(xb, B, C), Dense(dxb, B, C), Dense(dxb, B, C));  // in place
                    })
                    .ok());
    const Mat<float> y = dev_->Download(yb, B, C), dx = dev_->Download(dxb, B, C);
    const double tol = a == nn::Activation::kRelu ? 0.0 : kTolTranscendental;
    std::printf("%s: y %.2e (double %.2e), dx %.2e (double %.2e)\n", nn::ActivationName(a), RelError(y_ref, y),
                RelError(y_d, y), RelError(dx_ref, dx), RelError(dx_d, dx));
    EXPECT_LE(RelError(y_ref, y), tol);
    EXPECT_LE(RelError(dx_ref, dx), tol);
    // The far tail, element-wise relative.
    if (a == nn::Activation::kGelu) {
      EXPECT_NEAR(y(0, 0) / y_d(0, 0), 1.0, 1e-5) << y(0, 0) << " vs " << y_d(0, 0);
    }
    EXPECT_TRUE(y.array().isFinite().all() && dx.array().isFinite().all());
  }
}

TEST_F(VkNnTest, GateMatchesItsFormula) {
  const int B = 1100, C = 27;
  const std::vector<float> p = RandomVec(C + 6, 90);
  const Mat<float> h0 = Random(B, C, 91), r = Random(B, C, 92), dh = Random(B, C, 93);
  const std::vector<float> g0 = RandomVec(p.size(), 94);
  const Eigen::Map<const nn::RowVec<float>> g(p.data() + 6, C);
  const Mat<float> h_ref = h0 + (r.array().rowwise() * g.array()).matrix();
  const Mat<float> dr_ref = (dh.array().rowwise() * g.array()).matrix();
  std::vector<float> dg_ref = g0;
  nn::AddColumnSums(dh.cwiseProduct(r), dg_ref.data() + 6);
  const vk::Buffer pb = dev_->Upload(p), h0b = dev_->Upload(h0), rb = dev_->Upload(r), dhb = dev_->Upload(dh);
  const vk::Buffer hb = dev_->Zeros(B * C), drb = dev_->Zeros(B * C), gb = dev_->Upload(g0);
  ASSERT_TRUE(dev_->Run([&](vk::Recorder& rec) {
                    k().Gate(rec, pb, 6, Dense(h0b, B, C), Dense(rb, B, C), Dense(hb, B, C));
                    k().GateGrad(rec, pb, 6, Dense(dhb, B, C), Dense(rb, B, C), Dense(drb, B, C), gb);
                  })
                  .ok());
  EXPECT_LT(RelError(h_ref, dev_->Download(hb, B, C)), kTol);
  EXPECT_LT(RelError(dr_ref, dev_->Download(drb, B, C)), kTol);
  const std::vector<float> dg = dev_->Download(gb, g0.size());
  EXPECT_LT(
      RelError(nn::ConstMatMap<float>(dg_ref.data(), 1, dg.size()), nn::ConstMatMap<float>(dg.data(), 1, dg.size())),
      kTol);
}

}  // namespace
}  // namespace streetsim::field::vknn
