// The extended field's Vulkan kernels (render/vulkan/field/nn/vk_nn_kernels.h) one at a time at
// spec 14's sizes (docs/field.md "Composition"): model dim 64 = 4 heads x 16, 7 tokens of 16
// Fourier + 128 features = 144, VAE latent 32, GRU hidden 32, for --rows Gaussians (token kernels
// on rows x 7). Each kernel is recorded --repeats times into one command buffer (barriers between)
// and submitted once; prints milliseconds per call (wall time of the submission / repeats: on
// lavapipe that is device time, on a GPU it includes one submission's latency spread over the
// repeats) and, for GEMMs, GMAC/s. Inputs are random normals; random data does not change these
// kernels' work.
//   vk_nn_bench [--rows 65536] [--repeats 10] [--lavapipe]
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/vulkan_engine.h"
#include "render/vulkan/field/nn/vk_nn_kernels.h"

using namespace streetsim;
using namespace streetsim::field;
namespace vk = streetsim::vulkan;
using vknn::Dense;
using vknn::View;

namespace {

struct Bench {
  std::unique_ptr<vk::Context> ctx;
  std::unique_ptr<vknn::NnKernels> k;
  int repeats = 10;

  vk::Buffer Random(size_t n, uint64_t seed) const {
    std::vector<float> v(n);
    std::mt19937_64 rng(seed);
    std::normal_distribution<float> g(0.0f, 0.5f);
    for (float& x : v) x = g(rng);
    auto b = vk::Buffer::Create(*ctx, n * 4, vk::Buffer::Kind::kDevice, "bench");
    if (!b.ok() || !vk::UploadBytes(*ctx, *b, v.data(), n * 4).ok()) {
      std::fprintf(stderr, "buffer of %zu floats: failed\n", n);
      std::exit(1);
    }
    return *std::move(b);
  }
  void Time(const char* name, const std::string& shape, double macs, const std::function<void(vk::Recorder&)>& f) {
    vk::DescriptorArena arena(ctx->device());
    auto record = [&](int n) {
      absl::Status status;
      const auto t0 = std::chrono::steady_clock::now();
      absl::Status s = ctx->SubmitAndWait([&](VkCommandBuffer cmd) {
        vk::Recorder rec(*ctx, cmd, &arena);
        for (int i = 0; i < n; ++i) {
          f(rec);
          rec.Barrier();
        }
        status = rec.status();
      });
      if (!status.ok() || !s.ok()) {
        std::fprintf(stderr, "%s: %s %s\n", name, status.ToString().c_str(), s.ToString().c_str());
        std::exit(1);
      }
      (void)arena.Reset();
      return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    };
    record(1);  // warm-up: pipelines, first-touch pages
    const double ms = record(repeats) / repeats;
    if (macs > 0) {
      std::printf("%-28s %-30s %10.3f %10.1f\n", name, shape.c_str(), ms, macs / (ms * 1e6));
    } else {
      std::printf("%-28s %-30s %10.3f %10s\n", name, shape.c_str(), ms, "");
    }
  }
};

}  // namespace

int main(int argc, char** argv) {
  uint32_t rows = 65536;
  Bench b;
  bool lavapipe = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--rows" && i + 1 < argc) {
      rows = static_cast<uint32_t>(std::atoi(argv[++i]));
    } else if (a == "--repeats" && i + 1 < argc) {
      b.repeats = std::max(1, std::atoi(argv[++i]));
    } else if (a == "--lavapipe") {
      lavapipe = true;
    } else {
      std::fprintf(stderr, "usage: vk_nn_bench [--rows 65536] [--repeats 10] [--lavapipe]\n");
      return 2;
    }
  }
  auto ctx = vk::Context::Create(lavapipe ? VulkanDevicePreference::kLavapipe : VulkanDevicePreference::kGpu);
  if (!ctx.ok()) {
    std::fprintf(stderr, "%s\n", ctx.status().ToString().c_str());
    return 1;
  }
  b.ctx = *std::move(ctx);
  auto k = vknn::NnKernels::Create(*b.ctx);
  if (!k.ok()) {
    std::fprintf(stderr, "%s\n", k.status().ToString().c_str());
    return 1;
  }
  b.k = *std::move(k);
  constexpr uint32_t T = 7, M = 64, H = 4, Dh = 16, Dt = 144, F = 128, L = 32, G = 32, In = 128;
  const uint32_t R = rows, RT = rows * T;
  if (auto s = b.k->Reserve(RT, In * M + M); !s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
    return 1;
  }
  std::printf("%s; %u rows, %d repeats\n", b.ctx->description().c_str(), rows, b.repeats);
  std::printf("%-28s %-30s %10s %10s\n", "kernel", "shape", "ms/call", "GMAC/s");

  const vk::Buffer params = b.Random(In * M + M + 4 * M, 1), grads = b.Random(In * M + M + 4 * M, 2);
  const vk::Buffer x = b.Random(size_t(RT) * Dt, 3), y = b.Random(size_t(RT) * Dt, 4), z = b.Random(size_t(RT) * Dt, 5);
  const vk::Buffer w = b.Random(size_t(RT) * M, 6), u = b.Random(size_t(RT) * M, 7);
  nn::LinearSpec lin{static_cast<int>(In), static_cast<int>(M), true, 0, size_t(In) * M};
  const double macs = double(R) * In * M;
  auto shape = [](uint32_t r, uint32_t a, uint32_t c) {
    return std::to_string(r) + " x " + std::to_string(a) + " -> " + std::to_string(c);
  };
  b.Time("Linear", shape(R, In, M), macs,
         [&](vk::Recorder& rec) { b.k->Linear(rec, lin, params, Dense(x, R, In), Dense(y, R, M), false); });
  b.Time("LinearInputGrad", shape(R, M, In), macs,
         [&](vk::Recorder& rec) { b.k->LinearInputGrad(rec, lin, params, Dense(y, R, M), Dense(z, R, In), false); });
  b.Time("LinearParamGrad", shape(R, In, M), macs,
         [&](vk::Recorder& rec) { b.k->LinearParamGrad(rec, lin, Dense(x, R, In), Dense(y, R, M), grads); });
  nn::LinearSpec kv{static_cast<int>(Dt), static_cast<int>(M), true, 0, size_t(Dt) * M};
  const vk::Buffer kvp = b.Random(Dt * M + M, 8);
  b.Time("Linear (token K/V proj.)", shape(RT, Dt, M), double(RT) * Dt * M,
         [&](vk::Recorder& rec) { b.k->Linear(rec, kv, kvp, Dense(x, RT, Dt), Dense(w, RT, M), false); });
  b.Time("Linear (token slice j=3)", shape(R, Dt, M), double(R) * Dt * M, [&](vk::Recorder& rec) {
    b.k->Linear(rec, kv, kvp, View{&x, 3 * Dt, R, Dt, T * Dt}, View{&w, 3 * M, R, M, T * M}, false);
  });
  b.Time("ColumnSums", std::to_string(R) + " x 64", 0,
         [&](vk::Recorder& rec) { b.k->ColumnSums(rec, Dense(y, R, M), grads, 0); });
  b.Time("Activation gelu", std::to_string(R) + " x 64", 0,
         [&](vk::Recorder& rec) { b.k->Activation(rec, nn::Activation::kGelu, Dense(y, R, M), Dense(z, R, M)); });
  b.Time("ActivationGrad gelu", std::to_string(R) + " x 64", 0, [&](vk::Recorder& rec) {
    b.k->ActivationGrad(rec, nn::Activation::kGelu, Dense(y, R, M), Dense(z, R, M), Dense(u, R, M));
  });
  const nn::LayerNormSpec ln{static_cast<int>(M), 1e-5, 0, M};
  b.Time("LayerNorm", std::to_string(R) + " x 64", 0, [&](vk::Recorder& rec) {
    b.k->LayerNorm(rec, ln, params, Dense(y, R, M), Dense(z, R, M), Dense(u, R, M), Dense(w, R, 1));
  });
  b.Time("LayerNormGrad", std::to_string(R) + " x 64", 0, [&](vk::Recorder& rec) {
    b.k->LayerNormGrad(rec, ln, params, Dense(u, R, M), Dense(w, R, 1), Dense(y, R, M), Dense(z, R, M), grads);
  });
  const nn::FourierTimeSpec fs{8, static_cast<int>(T), static_cast<int>(F)};
  b.Time("FourierTokens", std::to_string(R) + " x 7 x (16 + 128)", 0, [&](vk::Recorder& rec) {
    b.k->FourierTokens(rec, fs, Dense(w, R, T), Dense(y, R, T * F), Dense(x, R, T * Dt));
  });
  b.Time("VaeSample", std::to_string(R) + " x 32", 0, [&](vk::Recorder& rec) {
    b.k->VaeSample(rec, L, Dense(y, R, 2 * L), Dense(z, R, L), Dense(u, R, L), Dense(w, R, 1));
  });
  b.Time("VaeSampleGrad", std::to_string(R) + " x 32", 0, [&](vk::Recorder& rec) {
    b.k->VaeSampleGrad(rec, L, Dense(y, R, 2 * L), Dense(z, R, L), Dense(u, R, L), 0.1f, Dense(x, R, 2 * L));
  });
  const vk::Buffer a = b.Random(size_t(R) * H * T, 9), dv = b.Random(size_t(RT) * M, 10);
  b.Time("AttentionCore", std::to_string(R) + " x 7 tokens, 4 x 16", double(R) * 2 * T * M, [&](vk::Recorder& rec) {
    b.k->AttentionCore(rec, T, H, Dh, Dense(u, R, M), Dense(w, RT, M), Dense(x, RT, M), Dense(a, R, H * T),
                       Dense(z, R, M));
  });
  b.Time("AttentionCoreGrad", std::to_string(R) + " x 7 tokens, 4 x 16", double(R) * 4 * T * M, [&](vk::Recorder& rec) {
    b.k->AttentionCoreGrad(rec, T, H, Dh, Dense(u, R, M), Dense(w, RT, M), Dense(x, RT, M), Dense(a, R, H * T),
                           Dense(u, R, M), Dense(z, R, M), Dense(y, RT, M), Dense(dv, RT, M));
  });
  b.Time("GruStep", std::to_string(R) + " x 32", 0, [&](vk::Recorder& rec) {
    b.k->GruStep(rec, G, Dense(x, R, 3 * G), Dense(y, R, 3 * G), Dense(u, R, G), Dense(w, R, G), Dense(z, R, 3 * G));
  });
  b.Time("GruStepGrad", std::to_string(R) + " x 32", 0, [&](vk::Recorder& rec) {
    b.k->GruStepGrad(rec, G, Dense(y, R, 3 * G), Dense(z, R, 3 * G), Dense(u, R, G), Dense(w, R, G), Dense(x, R, 3 * G),
                     Dense(x, R, 3 * G, uint32_t(R) * 3 * G), Dense(u, R, G));
  });
  return 0;
}
