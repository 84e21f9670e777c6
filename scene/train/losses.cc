#include "scene/train/losses.h"

#include <algorithm>
#include <cmath>

namespace streetsim::train {
namespace {

constexpr int kWin = 11;
constexpr int kHalf = 5;

struct Window {
  float w[kWin];
  Window() {
    double sum = 0, v[kWin];
    for (int k = 0; k < kWin; ++k) sum += v[k] = std::exp(-(k - kHalf) * (k - kHalf) / (2 * 1.5 * 1.5));
    for (int k = 0; k < kWin; ++k) w[k] = static_cast<float>(v[k] / sum);
  }
};
const Window& Win() {
  static const Window w;
  return w;
}

// Sum of v[0..n) in fixed-size blocks summed in order (deterministic for any thread count).
constexpr size_t kBlock = 4096;

// Horizontal 11-tap blur of one zero-padded row: dst[x] = sum_k w[k] row[x + k] (row holds
// kHalf zeros on each side), taps summed in k order.
// The taps are summed in a register per pixel (one store per output instead of one load, add and
// store per tap); same order, so the same bits.
inline void BlurRowH(const float* __restrict row, float* __restrict dst, int width) {
  const Window& win = Win();
  float w[kWin];
  for (int k = 0; k < kWin; ++k) w[k] = win.w[k];
  for (int x = 0; x < width; ++x) {
    float acc = 0;
#pragma GCC unroll 11
    for (int k = 0; k < kWin; ++k) acc += w[k] * row[x + k];
    dst[x] = acc;
  }
}

// Vertical 11-tap blur at row y of a plane [H][W] (zero padding), taps in k order.
inline void BlurRowV(const float* __restrict plane, float* __restrict dst, int y, int width, int height) {
  const float* w = Win().w;
  if (y >= kHalf && y + kHalf < height) {  // all taps inside: sum in a register, as BlurRowH
    const float* r[kWin];
    float wk[kWin];
    for (int k = 0; k < kWin; ++k) {
      r[k] = plane + static_cast<size_t>(y + k - kHalf) * width;
      wk[k] = w[k];
    }
#pragma GCC ivdep
    for (int x = 0; x < width; ++x) {
      float acc = 0;
#pragma GCC unroll 11
      for (int k = 0; k < kWin; ++k) acc += wk[k] * r[k][x];
      dst[x] = acc;
    }
    return;
  }
  for (int x = 0; x < width; ++x) dst[x] = 0;
  for (int k = 0; k < kWin; ++k) {
    const int yy = y + k - kHalf;
    if (yy < 0 || yy >= height) continue;
    const float wk = w[k];
    const float* s = plane + static_cast<size_t>(yy) * width;
    for (int x = 0; x < width; ++x) dst[x] += wk * s[x];
  }
}

// Scratch kept across calls (the training loop calls these every iteration on the same size):
// no allocation or page faults per call.
struct SsimScratch {
  std::vector<float> hb;      // horizontally blurred planes: [3 channels][5: x, y, xx, yy, xy][H][W]
  std::vector<float> dm;      // d-maps A, B, C: [3][3][H][W], then their horizontal blurs in hb
  std::vector<double> rows;   // per (row, channel) SSIM sums
};
SsimScratch& Scratch() {
  thread_local SsimScratch s;
  return s;
}
struct RowScratch {
  std::vector<float> buf;
  float* Get(size_t n) {
    if (buf.size() < n) buf.resize(n);
    return buf.data();
  }
};
float* RowBuf(size_t n) {
  thread_local RowScratch r;
  return r.Get(n);
}

// One row of the SSIM map from the blurred moments mu = [mu_x, mu_y, E[xx], E[yy], E[xy]] (each
// W long) and, with A non-null, its d-maps (A: d/d mu_x, B: d/d E[xx], C: d/d E[xy]). A function
// of its own: with every pointer __restrict at function scope the loop vectorises (inlined into
// the lambda it did not, divisions included).
void SsimRow(const float* __restrict mu, size_t W, float* __restrict s_out, float* __restrict A,
             float* __restrict B, float* __restrict C) {
  const float C1 = 0.01f * 0.01f, C2 = 0.03f * 0.03f;
  const float* __restrict mux = mu;
  const float* __restrict muy = mu + W;
  const float* __restrict exx = mu + 2 * W;
  const float* __restrict eyy = mu + 3 * W;
  const float* __restrict exy = mu + 4 * W;
  if (A != nullptr) {
    for (size_t x = 0; x < W; ++x) {
      const float mx = mux[x], my = muy[x];
      const float sxx = exx[x] - mx * mx, syy = eyy[x] - my * my, sxy = exy[x] - mx * my;
      const float n1 = 2 * mx * my + C1, n2 = 2 * sxy + C2;
      const float d1 = mx * mx + my * my + C1, d2 = sxx + syy + C2;
      const float s = (n1 * n2) / (d1 * d2);
      s_out[x] = s;
      const float inv = 1.0f / (d1 * d2);
      A[x] = 2 * my * (n2 - n1) * inv - 2 * mx * s * (1 / d1 - 1 / d2);
      B[x] = -s / d2;
      C[x] = 2 * n1 * inv;
    }
  } else {
    for (size_t x = 0; x < W; ++x) {
      const float mx = mux[x], my = muy[x];
      const float sxx = exx[x] - mx * mx, syy = eyy[x] - my * my, sxy = exy[x] - mx * my;
      const float n1 = 2 * mx * my + C1, n2 = 2 * sxy + C2;
      const float d1 = mx * mx + my * my + C1, d2 = sxx + syy + C2;
      s_out[x] = (n1 * n2) / (d1 * d2);
    }
  }
}

}  // namespace

double L1Loss(ThreadPool& pool, const float* render, const float* target, size_t n, float weight, float* grad) {
  const float g = weight / static_cast<float>(n);
  const size_t blocks = (n + kBlock - 1) / kBlock;
  std::vector<double> partial(blocks, 0.0);
  pool.ParallelFor(static_cast<int64_t>(blocks), 8, [&](int64_t b, int64_t e, int) {
    for (int64_t blk = b; blk < e; ++blk) {
      const size_t j0 = blk * kBlock, j1 = std::min(n, j0 + kBlock);
      double s = 0;
      for (size_t j = j0; j < j1; ++j) {
        const float d = render[j] - target[j];
        s += std::abs(d);
        if (grad) grad[j] += d > 0 ? g : (d < 0 ? -g : 0.0f);
      }
      partial[blk] = s;
    }
  });
  double s = 0;
  for (double p : partial) s += p;
  return s / static_cast<double>(n);
}

// Fused: per row, the 5 products are blurred horizontally straight from the interleaved images;
// the vertical blur of a row is followed at once by the SSIM map and its 3 d-maps (never stored
// as planes); with a gradient, the d-maps are blurred the same way and the vertical pass adds the
// gradient. Same taps in the same order as a plain separable blur.
double Ssim(ThreadPool& pool, const float* render, const float* target, int width, int height, float weight,
            float* grad) {
  const size_t W = static_cast<size_t>(width);
  const size_t plane = W * height;
  SsimScratch& sc = Scratch();
  sc.hb.resize(plane * 15);
  if (grad) sc.dm.resize(plane * 9);
  sc.rows.assign(static_cast<size_t>(height) * 3, 0.0);
  float* hb = sc.hb.data();
  float* dm = sc.dm.data();
  constexpr int64_t kRows = 4;
  // Horizontal blur of x, y, xx, yy, xy.
  pool.ParallelFor(height, kRows, [&](int64_t b, int64_t e, int) {
    const size_t padded = W + 2 * kHalf;
    float* buf = RowBuf(padded * 5);
    std::fill(buf, buf + padded * 5, 0.0f);
    for (int64_t y = b; y < e; ++y) {
      for (int c = 0; c < 3; ++c) {
        float* px = buf + kHalf;
        float* py = px + padded;
        float* pxx = py + padded;
        float* pyy = pxx + padded;
        float* pxy = pyy + padded;
        const float* r = render + y * W * 3 + c;
        const float* t = target + y * W * 3 + c;
        for (size_t x = 0; x < W; ++x) {
          const float a = r[x * 3], v = t[x * 3];
          px[x] = a, py[x] = v, pxx[x] = a * a, pyy[x] = v * v, pxy[x] = a * v;
        }
        for (int q = 0; q < 5; ++q) BlurRowH(buf + q * padded, hb + (c * 5 + q) * plane + y * W, width);
      }
    }
  });
  // Vertical blur, SSIM map, d-maps (A: d/d mu_x, B: d/d E[xx], C: d/d E[xy]).
  pool.ParallelFor(height, kRows, [&](int64_t b, int64_t e, int) {
    float* mu = RowBuf(W * 6);
    float* srow = mu + 5 * W;  // the row's SSIM values, summed in order below
    for (int64_t y = b; y < e; ++y) {
      for (int c = 0; c < 3; ++c) {
        for (int q = 0; q < 5; ++q) BlurRowV(hb + (c * 5 + q) * plane, mu + q * W, static_cast<int>(y), width, height);
        double sum = 0;
        if (grad) {
          SsimRow(mu, W, srow, dm + (c * 3 + 0) * plane + y * W, dm + (c * 3 + 1) * plane + y * W,
                  dm + (c * 3 + 2) * plane + y * W);
        } else {
          SsimRow(mu, W, srow, nullptr, nullptr, nullptr);
        }
        // A separate in-order double sum: inside the loops above it kept them scalar.
        for (size_t x = 0; x < W; ++x) sum += srow[x];
        sc.rows[y * 3 + c] = sum;
      }
    }
  });
  double total = 0;
  for (double r : sc.rows) total += r;
  const double mean = total / static_cast<double>(plane * 3);
  if (!grad) return mean;
  // Horizontal blur of the d-maps (into hb's first 9 planes).
  pool.ParallelFor(height, kRows, [&](int64_t b, int64_t e, int) {
    const size_t padded = W + 2 * kHalf;
    float* buf = RowBuf(padded);
    std::fill(buf, buf + padded, 0.0f);
    for (int64_t y = b; y < e; ++y) {
      for (int p = 0; p < 9; ++p) {
        std::copy(dm + p * plane + y * W, dm + p * plane + (y + 1) * W, buf + kHalf);
        BlurRowH(buf, hb + p * plane + y * W, width);
      }
    }
  });
  const float scale = weight / static_cast<float>(plane * 3);
  // Vertical blur and the gradient: scale * (A + 2 x B + y C).
  pool.ParallelFor(height, kRows, [&](int64_t b, int64_t e, int) {
    float* abc = RowBuf(W * 3);
    for (int64_t y = b; y < e; ++y) {
      for (int c = 0; c < 3; ++c) {
        for (int j = 0; j < 3; ++j) BlurRowV(hb + (c * 3 + j) * plane, abc + j * W, static_cast<int>(y), width, height);
        const float* r = render + y * W * 3 + c;
        const float* t = target + y * W * 3 + c;
        float* g = grad + y * W * 3 + c;
        for (size_t x = 0; x < W; ++x) g[x * 3] += scale * (abc[x] + 2 * r[x * 3] * abc[W + x] + t[x * 3] * abc[2 * W + x]);
      }
    }
  });
  return mean;
}

double DepthLoss(const float* render_depth, const std::vector<DepthSample>& samples, float weight, float* grad) {
  size_t count = 0;
  for (const DepthSample& s : samples) count += (s.depth > 0.01f && s.depth < 80.0f);
  if (count == 0) return 0;
  double sum = 0;
  const float g = weight * 2.0f / static_cast<float>(count) / 80.0f;
  for (const DepthSample& s : samples) {
    if (!(s.depth > 0.01f && s.depth < 80.0f)) continue;
    const float r = render_depth[s.pixel] / 80.0f;
    const float rc = std::min(std::max(r, 0.0f), 1.0f);
    const float d = rc - std::min(std::max(s.depth / 80.0f, 0.0f), 1.0f);
    sum += static_cast<double>(d) * d;
    if (grad && r > 0.0f && r < 1.0f) grad[s.pixel] += g * d;
  }
  return sum / static_cast<double>(count);
}

double Psnr(const float* render, const float* target, size_t n) {
  double se = 0;
  for (size_t i = 0; i < n; ++i) {
    const double d = std::min(std::max(render[i], 0.0f), 1.0f) - std::min(std::max(target[i], 0.0f), 1.0f);
    se += d * d;
  }
  const double mse = se / static_cast<double>(n);
  return mse > 0 ? 10.0 * std::log10(1.0 / mse) : 100.0;
}

namespace {
constexpr float kLumaWeights[3] = {0.299f, 0.587f, 0.114f};
}  // namespace

void LuminanceRgb(const float* rgb, size_t pixels, float* y3) {
  for (size_t p = 0; p < pixels; ++p) {
    const float y = kLumaWeights[0] * rgb[p * 3] + kLumaWeights[1] * rgb[p * 3 + 1] + kLumaWeights[2] * rgb[p * 3 + 2];
    y3[p * 3] = y3[p * 3 + 1] = y3[p * 3 + 2] = y;
  }
}

void LuminanceBackward(const float* d_y3, size_t pixels, float* d_rgb) {
  for (size_t p = 0; p < pixels; ++p) {
    const float g = d_y3[p * 3] + d_y3[p * 3 + 1] + d_y3[p * 3 + 2];
    for (int c = 0; c < 3; ++c) d_rgb[p * 3 + c] += kLumaWeights[c] * g;
  }
}

}  // namespace streetsim::train
