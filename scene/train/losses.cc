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

// Separable Gaussian blur with zero padding of `count` planes [count][H][W] (in -> out).
void Blur(ThreadPool& pool, const float* in, float* out, int count, int width, int height, std::vector<float>* tmp) {
  const size_t plane = static_cast<size_t>(width) * height;
  tmp->resize(plane * count);
  const float* w = Win().w;
  // Horizontal.
  pool.ParallelFor(static_cast<int64_t>(count) * height, 16, [&](int64_t b, int64_t e, int) {
    std::vector<float> row(width + 2 * kHalf, 0.0f);
    for (int64_t r = b; r < e; ++r) {
      const float* src = in + r * width;
      std::copy(src, src + width, row.begin() + kHalf);
      float* dst = tmp->data() + r * width;
      for (int x = 0; x < width; ++x) dst[x] = 0;
      for (int k = 0; k < kWin; ++k) {
        const float wk = w[k];
        const float* s = row.data() + k;
        for (int x = 0; x < width; ++x) dst[x] += wk * s[x];
      }
    }
  });
  // Vertical.
  pool.ParallelFor(static_cast<int64_t>(count) * height, 16, [&](int64_t b, int64_t e, int) {
    for (int64_t r = b; r < e; ++r) {
      const int64_t p = r / height;
      const int y = static_cast<int>(r % height);
      float* dst = out + r * width;
      for (int x = 0; x < width; ++x) dst[x] = 0;
      for (int k = 0; k < kWin; ++k) {
        const int yy = y + k - kHalf;
        if (yy < 0 || yy >= height) continue;
        const float wk = w[k];
        const float* s = tmp->data() + (p * height + yy) * width;
        for (int x = 0; x < width; ++x) dst[x] += wk * s[x];
      }
    }
  });
}

// Sum of v[0..n) in fixed-size blocks summed in order (deterministic for any thread count).
double BlockSum(ThreadPool& pool, const float* v, size_t n) {
  constexpr size_t kBlock = 4096;
  const size_t blocks = (n + kBlock - 1) / kBlock;
  std::vector<double> partial(blocks, 0.0);
  pool.ParallelFor(static_cast<int64_t>(blocks), 4, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      double s = 0;
      for (size_t j = i * kBlock; j < std::min(n, (i + 1) * kBlock); ++j) s += v[j];
      partial[i] = s;
    }
  });
  double s = 0;
  for (double p : partial) s += p;
  return s;
}

}  // namespace

double L1Loss(ThreadPool& pool, const float* render, const float* target, size_t n, float weight, float* grad) {
  std::vector<float> absd(n);
  const float g = weight / static_cast<float>(n);
  pool.ParallelFor(static_cast<int64_t>(n), 1 << 15, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      const float d = render[i] - target[i];
      absd[i] = std::abs(d);
      if (grad) grad[i] += d > 0 ? g : (d < 0 ? -g : 0.0f);
    }
  });
  return BlockSum(pool, absd.data(), n) / static_cast<double>(n);
}

double Ssim(ThreadPool& pool, const float* render, const float* target, int width, int height, float weight,
            float* grad) {
  const size_t plane = static_cast<size_t>(width) * height;
  const size_t n3 = plane * 3;
  // Planes: x, y, xx, yy, xy per channel (5 x 3).
  std::vector<float> in(n3 * 5), mu(n3 * 5), tmp;
  pool.ParallelFor(static_cast<int64_t>(plane), 1 << 14, [&](int64_t b, int64_t e, int) {
    for (int c = 0; c < 3; ++c) {
      float* x = in.data() + (0 * 3 + c) * plane;
      float* y = in.data() + (1 * 3 + c) * plane;
      float* xx = in.data() + (2 * 3 + c) * plane;
      float* yy = in.data() + (3 * 3 + c) * plane;
      float* xy = in.data() + (4 * 3 + c) * plane;
      for (int64_t i = b; i < e; ++i) {
        const float a = render[i * 3 + c], t = target[i * 3 + c];
        x[i] = a;
        y[i] = t;
        xx[i] = a * a;
        yy[i] = t * t;
        xy[i] = a * t;
      }
    }
  });
  Blur(pool, in.data(), mu.data(), 15, width, height, &tmp);
  const float C1 = 0.01f * 0.01f, C2 = 0.03f * 0.03f;
  std::vector<float> smap(n3);
  std::vector<float> dmaps;  // A (d/d mu_x), B (d/d E[xx]), C (d/d E[xy]) per channel
  if (grad) dmaps.resize(n3 * 3);
  pool.ParallelFor(static_cast<int64_t>(n3), 1 << 14, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      const float mx = mu[0 * n3 + i], my = mu[1 * n3 + i];
      const float sxx = mu[2 * n3 + i] - mx * mx, syy = mu[3 * n3 + i] - my * my;
      const float sxy = mu[4 * n3 + i] - mx * my;
      const float n1 = 2 * mx * my + C1, n2 = 2 * sxy + C2;
      const float d1 = mx * mx + my * my + C1, d2 = sxx + syy + C2;
      const float s = (n1 * n2) / (d1 * d2);
      smap[i] = s;
      if (grad) {
        const float inv = 1.0f / (d1 * d2);
        dmaps[i] = 2 * my * (n2 - n1) * inv - 2 * mx * s * (1 / d1 - 1 / d2);
        dmaps[n3 + i] = -s / d2;
        dmaps[2 * n3 + i] = 2 * n1 * inv;
      }
    }
  });
  const double mean = BlockSum(pool, smap.data(), n3) / static_cast<double>(n3);
  if (grad) {
    std::vector<float> bd(n3 * 3);
    Blur(pool, dmaps.data(), bd.data(), 9, width, height, &tmp);
    const float scale = weight / static_cast<float>(n3);
    pool.ParallelFor(static_cast<int64_t>(plane), 1 << 14, [&](int64_t b, int64_t e, int) {
      for (int c = 0; c < 3; ++c) {
        const float* A = bd.data() + c * plane;
        const float* B = bd.data() + n3 + c * plane;
        const float* C = bd.data() + 2 * n3 + c * plane;
        for (int64_t i = b; i < e; ++i) {
          const float x = render[i * 3 + c], y = target[i * 3 + c];
          grad[i * 3 + c] += scale * (A[i] + 2 * x * B[i] + y * C[i]);
        }
      }
    });
  }
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

}  // namespace streetsim::train
