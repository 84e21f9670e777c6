// The extended field's Vulkan kernels (scene/field/vulkan/nn/vk_nn_kernels.h) against the cpu ops
// of scene/field/nn in float (and double, printed: the cpu double path is the reference that
// field_nn_test gradient-checks against finite differences, so the kernels' agreement with it is
// their gradient check). Odd sizes (rows not multiples of 64, widths not multiples of 16),
// token-slice views (offset j*D, stride T*D), accumulate on / off, more than one gradient chunk;
// same inputs twice = same bits; a NaN row stays in its row; bad views and a too small Reserve
// fail the recorder with a clear status. Runs on the first Vulkan device (lavapipe here); skips
// without one.
//
// Tolerances: relative L2 error per output / gradient group (sqrt(sum d^2 / sum ref^2)). The
// kernels and the cpu float ops sum the same terms in other orders (tiles, chunks); rounding
// gives about sqrt(n) * 6e-8 for a sum of n terms (n <= 1100 here: 2e-6), so kTol = 2e-5 keeps a
// 10x margin and still fails on any wrong index or term. The transcendental kernels (erf, exp,
// sin, tanh written out in GLSL) get kTolTranscendental = 1e-4 (their float formulas differ from
// glibc's / Eigen's by a few ulp, amplified in cancelling differences such as 1 - sigmoid).
#include "scene/field/vulkan/nn/vk_nn_kernels.h"

#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/nn/activation.h"
#include "scene/field/nn/attention.h"
#include "scene/field/nn/fourier_time.h"
#include "scene/field/nn/gru_cell.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"
#include "scene/field/nn/vae_sampler.h"

namespace streetsim::field::vknn {
namespace {

namespace vk = vulkan;
using nn::Mat;

constexpr double kTol = 2e-5;
constexpr double kTolTranscendental = 1e-4;

template <typename A, typename B>
double RelError(const A& ref, const B& x) {
  double num = 0, den = 0;
  for (Eigen::Index i = 0; i < ref.size(); ++i) {
    const double d = double(ref.data()[i]) - double(x.data()[i]);
    num += d * d;
    den += double(ref.data()[i]) * double(ref.data()[i]);
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

Mat<float> Random(Eigen::Index rows, Eigen::Index cols, uint64_t seed, float scale = 1.0f) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0.0f, scale);
  Mat<float> m(rows, cols);
  for (Eigen::Index i = 0; i < m.size(); ++i) m.data()[i] = g(rng);
  return m;
}
std::vector<float> RandomVec(size_t n, uint64_t seed, float scale = 1.0f) {
  const Mat<float> m = Random(1, static_cast<Eigen::Index>(n), seed, scale);
  return std::vector<float>(m.data(), m.data() + n);
}
Mat<double> D(const Mat<float>& m) { return m.cast<double>(); }

// The shared device, its kernels, and buffer helpers.
struct Dev {
  std::unique_ptr<vk::Context> ctx;
  std::unique_ptr<NnKernels> k;
  static Dev* Get() {
    static Dev* dev = [] {
      if (ListVulkanDevices().empty()) return static_cast<Dev*>(nullptr);
      auto ctx = vk::Context::Create(VulkanDevicePreference::kGpu);
      if (!ctx.ok()) return static_cast<Dev*>(nullptr);
      auto* d = new Dev;
      d->ctx = *std::move(ctx);
      auto k = NnKernels::Create(*d->ctx);
      EXPECT_TRUE(k.ok()) << k.status();
      if (!k.ok()) return static_cast<Dev*>(nullptr);
      d->k = *std::move(k);
      EXPECT_TRUE(d->k->Reserve(2048, 4096).ok());
      std::printf("device: %s\n", d->ctx->description().c_str());
      return d;
    }();
    return dev;
  }
  vk::Buffer Upload(const float* data, size_t n, const char* name = "test") const {
    auto b = vk::Buffer::Create(*ctx, std::max<size_t>(n, 1) * 4, vk::Buffer::Kind::kDevice, name);
    EXPECT_TRUE(b.ok()) << b.status();
    if (n > 0) {
      EXPECT_TRUE(vk::UploadBytes(*ctx, *b, data, n * 4).ok());
    }
    return *std::move(b);
  }
  vk::Buffer Upload(const std::vector<float>& v, const char* name = "test") const {
    return Upload(v.data(), v.size(), name);
  }
  vk::Buffer Upload(const Mat<float>& m, const char* name = "test") const {
    return Upload(m.data(), static_cast<size_t>(m.size()), name);
  }
  vk::Buffer Zeros(size_t n, const char* name = "test") const { return Upload(std::vector<float>(n, 0.0f), name); }
  std::vector<float> Download(const vk::Buffer& b, size_t n) const {
    std::vector<float> v(n);
    EXPECT_TRUE(vk::DownloadBytes(*ctx, b, v.data(), n * 4).ok());
    return v;
  }
  Mat<float> Download(const vk::Buffer& b, Eigen::Index rows, Eigen::Index cols) const {
    const std::vector<float> v = Download(b, static_cast<size_t>(rows * cols));
    return nn::ConstMatMap<float>(v.data(), rows, cols);
  }
  // Records `f`, submits, waits; the recorder's status.
  absl::Status Run(const std::function<void(vk::Recorder&)>& f) const {
    vk::DescriptorArena arena(ctx->device());
    absl::Status status;
    absl::Status submit = ctx->SubmitAndWait([&](VkCommandBuffer cmd) {
      vk::Recorder rec(*ctx, cmd, &arena);
      f(rec);
      rec.Barrier();
      status = rec.status();
    });
    if (!status.ok()) return status;
    return submit;
  }
};

class VkNnTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dev_ = Dev::Get();
    if (dev_ == nullptr) GTEST_SKIP() << "no Vulkan device on this machine";
  }
  NnKernels& k() { return *dev_->k; }
  Dev* dev_ = nullptr;
};

// W at 3, b elsewhere (not after W) or right after W, or no bias.
nn::LinearSpec MakeSpec(int in, int out, int bias_mode) {
  nn::LinearSpec s;
  s.in = in;
  s.out = out;
  s.bias = bias_mode != 0;
  s.w_offset = 3;
  s.b_offset = bias_mode == 1 ? 3 + size_t(in) * out + 5 : 3 + size_t(in) * out;
  return s;
}
size_t ParamCount(const nn::LinearSpec& s) { return s.w_offset + size_t(s.in) * s.out + 5 + s.out + 2; }

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
