// Speed of the extended field's cpu building blocks (scene/field/nn, docs/field.md "Extended field
// modules") at the sizes suggested by ../shared/docs/s3gaussian-spec.md section 14: forward and
// backward in float, one thread, rows in chunks of 256 (as the field's GEMMs), every chunk's
// cache reused (no allocation after the first chunk). The same random chunk input is reused for
// every chunk, so inputs are warm in cache (in a composed field they are produced just before).
// Prints µs per 1000 Gaussians and the forward multiply-adds per Gaussian, for the serving-cost
// estimate (method.md section 3: S3Gaussian's field ~20k MAC per Gaussian).
//   nn_bench [--gaussians 65536] [--repeats 5] [--tokens 7] [--chunk 256]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <functional>
#include <random>
#include <string>
#include <vector>

#include "scene/field/nn/activation.h"
#include "scene/field/nn/attention.h"
#include "scene/field/nn/bi_gru.h"
#include "scene/field/nn/fourier_time.h"
#include "scene/field/nn/gru_cell.h"
#include "scene/field/nn/layer_norm.h"
#include "scene/field/nn/linear.h"
#include "scene/field/nn/vae_sampler.h"

using namespace streetsim::field::nn;
using Clock = std::chrono::steady_clock;

namespace {

double ThreadCpuUs() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e6 + ts.tv_nsec * 1e-3;
}

void Check(const absl::Status& s) {
  if (!s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
    std::exit(1);
  }
}

template <typename S>
S Take(absl::StatusOr<S> s) {
  Check(s.status());
  return *std::move(s);
}

Mat<float> Random(Eigen::Index rows, Eigen::Index cols, std::mt19937_64& rng) {
  std::uniform_real_distribution<float> u(-1, 1);
  Mat<float> m(rows, cols);
  for (Eigen::Index i = 0; i < m.size(); ++i) m.data()[i] = u(rng);
  return m;
}

struct Op {
  std::string name, sizes;
  int64_t macs = 0;    // forward, per Gaussian
  size_t params = 0;
  std::function<void()> forward, backward;  // one chunk
};

struct Timing {
  double fwd_cpu_us = 0, bwd_cpu_us = 0, wall_us = 0;  // per 1000 Gaussians, mean over repeats
};

// Thread CPU time per call (the machine is shared: wall time depends on the others' load), wall
// time of the whole run.
Timing Measure(const Op& op, int64_t gaussians, int chunk, int repeats) {
  const int64_t chunks = std::max<int64_t>(1, gaussians / chunk);
  op.forward();  // warm-up: sizes the caches
  op.backward();
  Timing t;
  const auto w0 = Clock::now();
  for (int r = 0; r < repeats; ++r) {
    for (int64_t c = 0; c < chunks; ++c) {
      const double t0 = ThreadCpuUs();
      op.forward();
      const double t1 = ThreadCpuUs();
      op.backward();
      const double t2 = ThreadCpuUs();
      t.fwd_cpu_us += t1 - t0;
      t.bwd_cpu_us += t2 - t1;
    }
  }
  t.wall_us = std::chrono::duration<double, std::micro>(Clock::now() - w0).count();
  const double scale = 1000.0 / (double(chunks) * chunk * repeats);
  t.fwd_cpu_us *= scale;
  t.bwd_cpu_us *= scale;
  t.wall_us *= scale;
  return t;
}

}  // namespace

int main(int argc, char** argv) {
  int64_t gaussians = 65536;
  int repeats = 5, tokens = 7, chunk = 256;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--gaussians") && i + 1 < argc) gaussians = std::max(1L, std::atol(argv[++i]));
    else if (!std::strcmp(argv[i], "--repeats") && i + 1 < argc) repeats = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--tokens") && i + 1 < argc) tokens = std::max(1, std::atoi(argv[++i]));
    else if (!std::strcmp(argv[i], "--chunk") && i + 1 < argc) chunk = std::max(1, std::atoi(argv[++i]));
    else {
      std::fprintf(stderr, "usage: nn_bench [--gaussians N] [--repeats R] [--tokens K] [--chunk B]\n");
      return 2;
    }
  }
  // Suggested sizes (spec 14): model dim 64 = 4 heads x 16, VAE latent 32 + 32, Bi-GRU hidden 32
  // per direction, K temporal tokens; HexPlane feature 128; Fourier frequencies 8; a temporal token
  // is [sin, cos (16), space-time plane features (128)] = 144.
  constexpr int kFeature = 128, kModel = 64, kHeads = 4, kLatent = 32, kHidden = 32, kFreq = 8;
  const int token_dim = 2 * kFreq + kFeature;
  const int b = chunk;
  std::mt19937_64 rng(1);
  NnLayout layout;
  const LinearSpec lin128 = Take(MakeLinear(&layout, "lin128", kFeature, kModel));
  const LinearSpec lin64 = Take(MakeLinear(&layout, "lin64", kModel, kModel));
  const LayerNormSpec norm = Take(MakeLayerNorm(&layout, "norm", kModel));
  const FourierTimeSpec fourier = Take(MakeFourierTime(kFreq, tokens, kFeature));
  const AttentionSpec attn = Take(MakeAttention(&layout, "attn", kModel, token_dim, tokens, kHeads, kModel));
  const LinearSpec vae_lin = Take(MakeLinear(&layout, "vae", kFeature, 2 * kLatent));
  const VaeSpec vae = Take(MakeVae(kLatent));
  const GruCellSpec cell = Take(MakeGruCell(&layout, "cell", token_dim, kHidden));
  const BiGruSpec bigru = Take(MakeBiGru(&layout, "bigru", tokens, token_dim, kHidden, kModel));
  std::vector<float> params(layout.total()), grads(layout.total(), 0.0f);
  for (const LinearSpec* l : {&lin128, &lin64, &vae_lin}) InitLinear(*l, rng, params.data());
  InitLayerNorm(norm, params.data());
  InitAttention(attn, rng, params.data());
  InitGruCell(cell, rng, params.data());
  InitBiGru(bigru, rng, params.data());
  const float* p = params.data();
  float* g = grads.data();

  const Mat<float> x128 = Random(b, kFeature, rng), x64 = Random(b, kModel, rng), dy64 = Random(b, kModel, rng);
  const Mat<float> times = Random(b, tokens, rng), feats = Random(b, int64_t{tokens} * kFeature, rng);
  const Mat<float> toks = Random(b, int64_t{tokens} * token_dim, rng);
  const Mat<float> dtoks = Random(b, int64_t{tokens} * token_dim, rng);
  const Mat<float> eps = Random(b, kLatent, rng), dz = Random(b, kLatent, rng), dh = Random(b, kHidden, rng);
  const Mat<float> h0 = Random(b, kHidden, rng);
  Mat<float> y, dx, dx2, tmp;
  LinearCache<float> lc;
  LayerNormCache<float> nc;
  ActivationCache<float> ac;
  FourierTimeCache<float> fc;
  AttentionCache<float> atc;
  VaeCache<float> vc;
  GruCellCache<float> gc;
  BiGruCache<float> bc;
  Mat<float> mu_logvar, z, dmv;

  auto count = [&](const std::string& prefix) {
    size_t n = 0;
    for (const NnParamBlock& blk : layout.blocks())
      if (blk.name.rfind(prefix, 0) == 0) n += blk.count;
    return n;
  };
  std::vector<Op> ops;
  ops.push_back({"linear", "128 -> 64", lin128.Macs(), count("lin128."),
                 [&] { Check(LinearForward<float>(lin128, p, x128, &y, &lc)); },
                 [&] { Check(LinearBackward<float>(lin128, p, lc, dy64, &dx, g)); }});
  ops.push_back({"linear", "64 -> 64", lin64.Macs(), count("lin64."),
                 [&] { Check(LinearForward<float>(lin64, p, x64, &y, &lc)); },
                 [&] { Check(LinearBackward<float>(lin64, p, lc, dy64, &dx, g)); }});
  ops.push_back({"layer_norm", "64", 0, count("norm."), [&] { Check(LayerNormForward<float>(norm, p, x64, &y, &nc)); },
                 [&] { Check(LayerNormBackward<float>(norm, p, nc, dy64, &dx, g)); }});
  for (Activation a : {Activation::kRelu, Activation::kGelu, Activation::kSilu}) {
    ops.push_back({ActivationName(a), "64", 0, 0, [&, a] { ActivationForward<float>(a, x64, &y, &ac); },
                   [&, a] { Check(ActivationBackward<float>(a, ac, dy64, &dx)); }});
  }
  const std::string tok = std::to_string(tokens);
  ops.push_back({"fourier_time", "m 8, " + tok + " x (16 + 128)", 0, 0,
                 [&] { Check(FourierTimeForward<float>(fourier, times, feats, &y, &fc)); },
                 [&] { Check(FourierTimeBackward<float>(fourier, fc, dtoks, &dx, &dx2)); }});
  ops.push_back({"attention", "q 64, " + tok + " x 144, 4 x 16, +LN", attn.Macs(), count("attn."),
                 [&] { Check(AttentionForward<float>(attn, p, x64, toks, &y, &atc)); },
                 [&] { Check(AttentionBackward<float>(attn, p, atc, dy64, &dx, &dx2, g)); }});
  ops.push_back({"vae", "128 -> 32+32, sample, KL", vae_lin.Macs(), count("vae."),
                 [&] {
                   Check(LinearForward<float>(vae_lin, p, x128, &mu_logvar, &lc));
                   Check(VaeSampleForward<float>(vae, mu_logvar, eps, &z, &vc));
                 },
                 [&] {
                   Check(VaeSampleBackward<float>(vae, vc, dz, &dmv));
                   float kl = 0;
                   Check(VaeKl<float>(vae, mu_logvar, 1e-4f, &kl, &dmv));
                   Check(LinearBackward<float>(vae_lin, p, lc, dmv, &dx, g));
                 }});
  ops.push_back({"gru_cell", "144 -> 32, one step", cell.Macs(), count("cell."),
                 [&] { Check(GruCellForward<float>(cell, p, toks.leftCols(token_dim), h0, &y, &gc)); },
                 [&] { Check(GruCellBackward<float>(cell, p, gc, dh, &dx, &dx2, g)); }});
  ops.push_back({"bi_gru", tok + " x 144, 2 x 32 -> 64", bigru.Macs(), count("bigru."),
                 [&] { Check(BiGruForward<float>(bigru, p, toks, &y, &bc)); },
                 [&] { Check(BiGruBackward<float>(bigru, p, bc, dy64, &dx, g)); }});

  std::printf("nn_bench: float, 1 thread, chunks of %d rows, %lld Gaussians, %d repeats, K = %d tokens\n", chunk,
              static_cast<long long>(gaussians), repeats, tokens);
  std::printf("| op | sizes | params | fwd MAC / Gaussian | fwd CPU us / 1k | bwd CPU us / 1k | fwd+bwd CPU us / 1k | "
              "fwd+bwd wall us / 1k |\n|---|---|---|---|---|---|---|---|\n");
  for (const Op& op : ops) {
    const Timing t = Measure(op, gaussians, chunk, repeats);
    std::printf("| %s | %s | %zu | %lld | %.1f | %.1f | %.1f | %.1f |\n", op.name.c_str(), op.sizes.c_str(), op.params,
                static_cast<long long>(op.macs), t.fwd_cpu_us, t.bwd_cpu_us, t.fwd_cpu_us + t.bwd_cpu_us, t.wall_us);
  }
  // A plausible composition (not built; docs/field.md): encoder Linear(128 -> 64) + 2 x (Linear 64
  // -> 64, LN, ReLU), VAE Linear(64 -> 32+32), query Linear(32 -> 64), attention over K tokens,
  // Bi-GRU over them, S3Gaussian's heads (64 -> 64 -> 3, 64 -> 64 -> 48).
  const int64_t heads = 64 * 64 + 64 * 3 + 64 * 64 + 64 * 48;
  const int64_t sketch = 128 * 64 + 2 * 64 * 64 + 64 * 64 + 32 * 64 + attn.Macs() + bigru.Macs() + heads;
  std::printf("\ncomposition sketch (encoder, VAE, attention, Bi-GRU, S3Gaussian heads): %lld MAC / Gaussian "
              "forward (S3Gaussian's field: 19 650), plus %d x the space-time plane lookups\n",
              static_cast<long long>(sketch), tokens);
  return 0;
}
