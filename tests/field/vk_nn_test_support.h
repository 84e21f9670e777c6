// Shared by the extended field's Vulkan kernel tests (vk_nn_kernels_test.cc: Linear, determinism,
// NaN rows, recorder errors, activations; vk_nn_sequence_test.cc: LayerNorm, temporal tokens, VAE,
// attention, GRU): the device (first Vulkan device, once per process), buffer helpers, the
// fixture that skips without a device, and the tolerances.
//
// Tolerances: relative L2 error per output / gradient group (sqrt(sum d^2 / sum ref^2)). The
// kernels and the cpu float ops sum the same terms in other orders (tiles, chunks); rounding
// gives about sqrt(n) * 6e-8 for a sum of n terms (n <= 1100 here: 2e-6), so kTol = 2e-5 keeps a
// 10x margin and still fails on any wrong index or term. The transcendental kernels (erf, exp,
// sin, tanh written out in GLSL) get kTolTranscendental = 1e-4 (their float formulas differ from
// glibc's / Eigen's by a few ulp, amplified in cancelling differences such as 1 - sigmoid).
#pragma once

#include "render/vulkan/field/nn/vk_nn_kernels.h"

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

namespace vk = vulkan;
using nn::Mat;

constexpr double kTol = 2e-5;
constexpr double kTolTranscendental = 1e-4;

template <typename A, typename B>
inline double RelError(const A& ref, const B& x) {
  double num = 0, den = 0;
  for (Eigen::Index i = 0; i < ref.size(); ++i) {
    const double d = double(ref.data()[i]) - double(x.data()[i]);
    num += d * d;
    den += double(ref.data()[i]) * double(ref.data()[i]);
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

inline Mat<float> Random(Eigen::Index rows, Eigen::Index cols, uint64_t seed, float scale = 1.0f) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> g(0.0f, scale);
  Mat<float> m(rows, cols);
  for (Eigen::Index i = 0; i < m.size(); ++i) m.data()[i] = g(rng);
  return m;
}
inline std::vector<float> RandomVec(size_t n, uint64_t seed, float scale = 1.0f) {
  const Mat<float> m = Random(1, static_cast<Eigen::Index>(n), seed, scale);
  return std::vector<float>(m.data(), m.data() + n);
}
inline Mat<double> D(const Mat<float>& m) { return m.cast<double>(); }

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
inline nn::LinearSpec MakeSpec(int in, int out, int bias_mode) {
  nn::LinearSpec s;
  s.in = in;
  s.out = out;
  s.bias = bias_mode != 0;
  s.w_offset = 3;
  s.b_offset = bias_mode == 1 ? 3 + size_t(in) * out + 5 : 3 + size_t(in) * out;
  return s;
}
inline size_t ParamCount(const nn::LinearSpec& s) { return s.w_offset + size_t(s.in) * s.out + 5 + s.out + 2; }

}  // namespace streetsim::field::vknn
