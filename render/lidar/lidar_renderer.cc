#include "render/lidar/lidar_renderer.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "render/common/projection_math.h"
#include "render/common/thread_pool.h"
#include "render/cpu/binning.h"
#include "render/cpu/simd_dispatch.h"
#include "render/lidar/lidar_kernels.h"

namespace streetsim {
namespace {

using lidar::kLowPassPx;
using lidar::kMaxAlpha;
using lidar::kMinAlpha;
using lidar::kMinTransmittance;
using lidar::kNearM;
using lidar::kTile;
using lidar::LidarSplat;
using lidar::Rect;

double Ms(std::chrono::steady_clock::time_point a, std::chrono::steady_clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

uint64_t SplitMix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

// Beam table in radians and per-segment slopes for the vectorised projection.
void BeamTableFloat(const LidarModel& model, std::vector<float>* elev, std::vector<float>* slope) {
  const int n = model.beams();
  elev->resize(n);
  slope->resize(n - 1);
  for (int b = 0; b < n; ++b) (*elev)[b] = static_cast<float>(model.BeamElevationRad(b));
  for (int k = 0; k + 1 < n; ++k) {
    (*slope)[k] = static_cast<float>(1.0 / (model.BeamElevationRad(k + 1) - model.BeamElevationRad(k)));
  }
}

// The scalar reference projection of Gaussians [begin, end) (libm, the model's double beam map).
void ProjectScalar(const lidar::LidarSoa& s, const LidarModel& model, const lidar::LidarProjectParams& p,
                   int64_t begin, int64_t end, lidar::LidarProjectOut* out) {
  const float* Rlw = p.R;
  const float* tlw = p.t;
  for (int64_t i = begin; i < end; ++i) {
    const float m[3] = {s.mx[i], s.my[i], s.mz[i]};
    const float px = Rlw[0] * m[0] + Rlw[1] * m[1] + Rlw[2] * m[2] + tlw[0];
    const float py = Rlw[3] * m[0] + Rlw[4] * m[1] + Rlw[5] * m[2] + tlw[1];
    const float pz = Rlw[6] * m[0] + Rlw[7] * m[1] + Rlw[8] * m[2] + tlw[2];
    const float rho2 = px * px + py * py;
    const float r2 = rho2 + pz * pz;
    const float range = std::sqrt(r2);
    if (!(range > p.near_m) || !(range < p.far_m)) continue;  // also rejects NaN
    const float rho = std::sqrt(rho2);
    if (!(rho > 1e-3f * range)) continue;  // straight up/down: no beam looks there
    const float opacity = 1.0f / (1.0f + std::exp(-s.opacity_logit[i]));
    if (!(opacity * 255.0f > 1.0f)) continue;

    // Sigma = R S S^T R^T (world frame).
    float R[9];
    const float q[4] = {s.qw[i], s.qx[i], s.qy[i], s.qz[i]};
    projection::QuatToRotation(q, R);
    const float ls[3] = {s.ls0[i], s.ls1[i], s.ls2[i]};
    const float sc[3] = {std::exp(std::clamp(ls[0], -30.0f, 30.0f)), std::exp(std::clamp(ls[1], -30.0f, 30.0f)),
                         std::exp(std::clamp(ls[2], -30.0f, 30.0f))};
    float Sg[6];
    projection::Covariance3D(R, sc, Sg);

    // Spherical projection and its Jacobian at the sensor-frame mean.
    //   u = (pi - atan2(y, x)) W / 2pi - 0.5:  du/dp = W/2pi (y, -x, 0) / rho^2
    //   v = beam(atan2(z, rho)):              dv/dp = beam'(el) (-x z / rho, -y z / rho, rho) / r^2
    const float elevation = std::atan2(pz, rho);
    double dbeam = 0;
    const float v = static_cast<float>(model.BeamCoordinate(elevation, &dbeam));
    const float u = static_cast<float>(model.ColumnCoordinate(std::atan2(py, px)));
    const float ku = p.cols_per_rad / rho2;
    const float kv = static_cast<float>(dbeam) / r2;
    const float J0[3] = {ku * py, -ku * px, 0.0f};
    const float J1[3] = {-kv * px * pz / rho, -kv * py * pz / rho, kv * rho};
    // T = J W (2x3), W = R_lidar_from_world.
    float T0[3], T1[3];
    for (int k = 0; k < 3; ++k) {
      T0[k] = J0[0] * Rlw[k] + J0[1] * Rlw[3 + k] + J0[2] * Rlw[6 + k];
      T1[k] = J1[0] * Rlw[k] + J1[1] * Rlw[3 + k] + J1[2] * Rlw[6 + k];
    }
    float cxx, cxy, cyy;
    projection::ProjectCovariance(T0, T1, Sg, kLowPassPx, &cxx, &cxy, &cyy);
    const float det = cxx * cyy - cxy * cxy;
    if (!(det > 0.0f) || !std::isfinite(det)) continue;
    const float inv_det = 1.0f / det;

    LidarSplat sp;
    sp.x = u;
    sp.y = v;
    sp.a = cyy * inv_det;
    sp.b = -cxy * inv_det;
    sp.c = cxx * inv_det;
    sp.opacity = opacity;
    sp.range = range;
    sp.refl = p.reflectance ? std::clamp(p.reflectance[i], 0.0f, 1.0f) : 0.5f;
    // The 3-sigma square intersected with the opacity box (as the camera path).
    const float mid = 0.5f * (cxx + cyy);
    const float lambda_max = mid + std::sqrt(std::max(0.1f, mid * mid - det));
    const float radius = std::ceil(3.0f * std::sqrt(lambda_max));
    const float d2 = 2.0f * std::log(opacity * 255.0f);
    sp.op_w = std::sqrt(d2 * cxx);
    sp.op_h = std::sqrt(d2 * cyy);
    const float half_w = std::min(radius, sp.op_w);
    const float half_h = std::min(radius, sp.op_h);
    if (!std::isfinite(sp.x) || !std::isfinite(sp.y) || !std::isfinite(half_w) || !std::isfinite(half_h)) {
      continue;
    }
    lidar::FillSplat(p, sp, half_w, half_h, out);
  }
}

// The scalar reference blend of tiles [tb, te): per pixel, std::exp, only the pixels inside each
// splat's opacity box.
void BlendScalar(const lidar::LidarBlendArgs& args, int64_t tb, int64_t te) {
  float T[kTile * kTile], D[kTile * kTile], I[kTile * kTile];
  const int B = args.beams, W = args.columns;
  for (int64_t tile = tb; tile < te; ++tile) {
    const int tx = static_cast<int>(tile % args.tiles_x), ty = static_cast<int>(tile / args.tiles_x);
    const int x0 = tx * kTile, y0 = ty * kTile;
    const int rows = std::min(kTile, B - y0), cols = std::min(kTile, W - x0);
    int live = rows * cols;
    for (int p = 0; p < kTile * kTile; ++p) {
      T[p] = 1.0f;
      D[p] = I[p] = 0.0f;
    }
    for (uint32_t j = args.tile_offsets[tile]; j < args.tile_offsets[tile + 1] && live > 0; ++j) {
      const LidarSplat s = args.splats[args.tile_ids[j]];
      // Only the tile's pixels inside the splat's opacity box (outside it opacity * G < 1/255:
      // an exact skip; within a listed tile the 3-sigma radius does not restrict, as in 3DGS).
      // Bounds clamped in float first so that huge boxes cannot overflow an int.
      auto lo = [](float v, int origin) {
        return std::max(0, static_cast<int>(std::ceil(std::max(v - origin, -1.0f))));
      };
      auto hi = [](float v, int origin, int n) {
        return std::min(n - 1, static_cast<int>(std::floor(std::min(v - origin, static_cast<float>(n)))));
      };
      const int r0 = lo(s.y - s.op_h, y0), r1 = hi(s.y + s.op_h, y0, rows);
      const int c0 = lo(s.x - s.op_w, x0), c1 = hi(s.x + s.op_w, x0, cols);
      for (int r = r0; r <= r1; ++r) {
        const float dy = s.y - static_cast<float>(y0 + r);
        for (int c = c0; c <= c1; ++c) {
          const int p = r * kTile + c;
          const float t = T[p];
          if (t <= 0.0f) continue;  // done
          const float dx = s.x - static_cast<float>(x0 + c);
          const float power = -0.5f * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
          if (power > 0.0f) continue;
          const float alpha = std::min(kMaxAlpha, s.opacity * std::exp(power));
          if (alpha < kMinAlpha) continue;
          const float test_T = t * (1.0f - alpha);
          if (test_T < kMinTransmittance) {
            T[p] = -t;  // done; this splat is not added
            --live;
            continue;
          }
          const float wgt = alpha * t;
          D[p] += wgt * s.range;
          I[p] += wgt * s.refl;
          T[p] = test_T;
        }
      }
    }
    for (int r = 0; r < rows; ++r) {
      for (int c = 0; c < cols; ++c) {
        const int p = r * kTile + c;
        const size_t pix = static_cast<size_t>(y0 + r) * W + x0 + c;
        args.T[pix] = T[p];
        args.range_sum[pix] = D[p];
        args.intensity_sum[pix] = I[p];
      }
    }
  }
}

using ProjectFn = void (*)(const lidar::LidarSoa&, const lidar::LidarProjectParams&, int64_t, int64_t,
                           lidar::LidarProjectOut*);
using BlendFn = void (*)(const lidar::LidarBlendArgs&, int64_t, int64_t);

}  // namespace

namespace lidar {

void FillSplat(const LidarProjectParams& p, const LidarSplat& sp, float half_w, float half_h,
               LidarProjectOut* out) {
  const int B = p.beams, W = p.columns;
  // Rows beyond the image: nothing to draw.
  if (sp.y + half_h < -0.5f || sp.y - half_h > B - 0.5f) return;
  const int tiles_x = p.tiles_x, tiles_y = p.tiles_y;
  auto rect_of = [&](float x) {
    auto clampi = [](float t, int hi) { return static_cast<int>(std::min(std::max(t, 0.0f), static_cast<float>(hi))); };
    // Pixel c samples coordinate c; tile t holds pixels [16 t, 16 t + 16) (as the camera path).
    Rect r;
    r.x0 = clampi(std::floor((x - half_w) / kTile), tiles_x);
    r.x1 = clampi(std::floor((x + half_w) / kTile) + 1, tiles_x);
    r.y0 = clampi(std::floor((sp.y - half_h) / kTile), tiles_y);
    r.y1 = clampi(std::floor((sp.y + half_h) / kTile) + 1, tiles_y);
    if (r.x1 <= r.x0 || r.y1 <= r.y0) r = Rect{0, 0, 0, 0};
    return r;
  };
  const uint32_t key = std::bit_cast<uint32_t>(sp.range);
  const Rect r = rect_of(sp.x);
  if (r.count() > 0) {
    out->splats[out->count] = sp;
    out->rects[out->count] = r;
    out->keys[out->count] = key;
    ++out->count;
  }
  // The seam behind the sensor: a splat reaching past either end of the columns is drawn
  // again one turn away (not when it spans more than half a turn: it would be drawn twice).
  if (half_w < 0.5f * W) {
    float x2 = 0;
    bool wrap = false;
    if (sp.x - half_w < -0.5f) { x2 = sp.x + W; wrap = true; }
    if (sp.x + half_w > W - 0.5f) { x2 = sp.x - W; wrap = true; }
    if (wrap) {
      const Rect r2 = rect_of(x2);
      if (r2.count() > 0) {
        out->splats[out->count] = sp;
        out->splats[out->count].x = x2;
        out->rects[out->count] = r2;
        out->keys[out->count] = key;
        ++out->count;
      }
    }
  }
}

}  // namespace lidar

struct LidarRenderer::Work {
  bool uploaded = false;
  lidar::LidarSoa soa;
  std::vector<float> elev, slope;
  // Projection output: block b of kProjectBlock Gaussians writes its splats (and seam copies)
  // densely from 2 b kProjectBlock on (LidarProjectOut); block_counts[b] of them.
  std::vector<LidarSplat> splats;
  std::vector<Rect> rects, sorted_rects;
  std::vector<uint32_t> block_keys, block_counts;
  std::vector<uint32_t> ids, keys, scratch_keys, scratch_ids;
  std::vector<uint32_t> tile_offsets, tile_ids, bin_counts;
};

LidarRenderer::LidarRenderer(int num_threads)
    : pool_(std::make_unique<ThreadPool>(num_threads)), work_(std::make_unique<Work>()) {}
LidarRenderer::~LidarRenderer() = default;

const char* LidarRenderer::SimdIsa() {
  switch (cpu::DetectSimdIsa()) {
    case cpu::SimdIsa::kAvx512: return "avx512";
    case cpu::SimdIsa::kAvx2: return "avx2";
    default: return "generic";
  }
}

size_t LidarRenderer::uploaded_size() const { return work_->uploaded ? work_->soa.n : 0; }

absl::Status LidarRenderer::Upload(const GaussianStore& store) {
  Work& w = *work_;
  w.uploaded = false;
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  const size_t n = store.size();
  if (n > (1u << 30)) return absl::InvalidArgumentError("too many Gaussians for the LiDAR renderer");
  lidar::LidarSoa& s = w.soa;
  s.n = n;
  for (auto* v : {&s.mx, &s.my, &s.mz, &s.ls0, &s.ls1, &s.ls2, &s.qw, &s.qx, &s.qy, &s.qz, &s.opacity_logit}) {
    v->resize(n);
  }
  pool_->ParallelFor(static_cast<int64_t>(n), 16384, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      s.mx[i] = store.means[i * 3];
      s.my[i] = store.means[i * 3 + 1];
      s.mz[i] = store.means[i * 3 + 2];
      s.ls0[i] = store.log_scales[i * 3];
      s.ls1[i] = store.log_scales[i * 3 + 1];
      s.ls2[i] = store.log_scales[i * 3 + 2];
      s.qw[i] = store.rotations[i * 4];
      s.qx[i] = store.rotations[i * 4 + 1];
      s.qy[i] = store.rotations[i * 4 + 2];
      s.qz[i] = store.rotations[i * 4 + 3];
      s.opacity_logit[i] = store.opacity_logits[i];
    }
  });
  w.uploaded = true;
  return absl::OkStatus();
}

absl::Status LidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                   const Eigen::Isometry3d& T_world_from_lidar,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  if (absl::Status s = Upload(store); !s.ok()) return s;
  return Render(model, T_world_from_lidar, options, out);
}

absl::Status LidarRenderer::Render(const LidarModel& model, const Eigen::Isometry3d& T_world_from_lidar,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  const auto t0 = std::chrono::steady_clock::now();
  Work& w = *work_;
  if (!w.uploaded) return absl::InvalidArgumentError("LidarRenderer: no scene uploaded");
  if (absl::Status s = model.Validate(); !s.ok()) return s;
  {
    const Eigen::Matrix3d R = T_world_from_lidar.linear();
    if (!T_world_from_lidar.matrix().allFinite() ||
        !(R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) || R.determinant() < 0) {
      return absl::InvalidArgumentError("T_world_from_lidar must be a finite rigid transform");
    }
  }
  const size_t n = w.soa.n;
  if (options.reflectance && options.reflectance->size() != n) {
    return absl::InvalidArgumentError(absl::StrCat("reflectance has ", options.reflectance->size(),
                                                   " values for ", n, " Gaussians"));
  }
  const bool simd = options.kernel != LidarRenderOptions::Kernel::kScalar;
  const bool avx2 = options.kernel == LidarRenderOptions::Kernel::kSimdAvx2;
  const ProjectFn project_simd =
      avx2 ? lidar::simd_avx2::ProjectRange
           : cpu::PickSimd<ProjectFn>(lidar::simd_avx2::ProjectRange, lidar::simd_avx512::ProjectRange);
  const BlendFn blend =
      !simd ? BlendScalar
            : avx2 ? lidar::simd_avx2::BlendTiles
                   : cpu::PickSimd<BlendFn>(lidar::simd_avx2::BlendTiles, lidar::simd_avx512::BlendTiles);

  const int B = model.beams(), W = model.columns;
  const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (B + kTile - 1) / kTile;
  const int num_tiles = tiles_x * tiles_y;

  // ---- Projection ----
  const Eigen::Isometry3d T_lidar_from_world = T_world_from_lidar.inverse();
  lidar::LidarProjectParams params;
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) params.R[r * 3 + k] = static_cast<float>(T_lidar_from_world.linear()(r, k));
    params.t[r] = static_cast<float>(T_lidar_from_world.translation()[r]);
  }
  params.near_m = std::max(kNearM, static_cast<float>(model.min_range_m));
  params.far_m = static_cast<float>(model.max_range_m);
  params.columns = W;
  params.beams = B;
  params.tiles_x = tiles_x;
  params.tiles_y = tiles_y;
  params.cols_per_rad = static_cast<float>(W / (2 * M_PI));
  BeamTableFloat(model, &w.elev, &w.slope);
  params.elev = w.elev.data();
  params.slope = w.slope.data();
  params.reflectance = options.reflectance ? options.reflectance->data() : nullptr;
  constexpr int64_t kProjectBlock = 4096;
  const int64_t blocks = (static_cast<int64_t>(n) + kProjectBlock - 1) / kProjectBlock;
  w.splats.resize(2 * n);
  w.rects.resize(2 * n);
  w.block_keys.resize(2 * n);
  w.block_counts.assign(blocks + 1, 0);
  pool_->ParallelFor(blocks, 1, [&](int64_t b0, int64_t b1, int) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t begin = blk * kProjectBlock, end = std::min<int64_t>(static_cast<int64_t>(n), begin + kProjectBlock);
      const size_t base = static_cast<size_t>(2 * begin);
      lidar::LidarProjectOut pout{w.splats.data() + base, w.rects.data() + base, w.block_keys.data() + base, 0};
      if (simd) {
        project_simd(w.soa, params, begin, end, &pout);
      } else {
        ProjectScalar(w.soa, model, params, begin, end, &pout);
      }
      w.block_counts[blk + 1] = pout.count;
    }
  });
  // The sort's input: (key, buffer position) of every splat, in Gaussian order.
  for (int64_t blk = 0; blk < blocks; ++blk) w.block_counts[blk + 1] += w.block_counts[blk];
  w.ids.resize(w.block_counts[blocks]);
  w.keys.resize(w.ids.size());
  pool_->ParallelFor(blocks, 16, [&](int64_t b0, int64_t b1, int) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const uint32_t o = w.block_counts[blk], cnt = w.block_counts[blk + 1] - o;
      const uint32_t base = static_cast<uint32_t>(2 * blk * kProjectBlock);
      for (uint32_t k = 0; k < cnt; ++k) {
        w.ids[o + k] = base + k;
        w.keys[o + k] = w.block_keys[base + k];
      }
    }
  });
  const auto t1 = std::chrono::steady_clock::now();

  // ---- Sort by range (ties: entry index), bin into tiles ----
  const int64_t V = static_cast<int64_t>(w.ids.size());
  // The camera binning's stable radix sort (single-threaded: a pooled version was no faster
  // on 2 cores, measured back to back).
  cpu::RadixSortPairs(&w.keys, &w.ids, &w.scratch_keys, &w.scratch_ids);
  {
    // Binning: per-chunk counts, a scan in (tile, chunk) order, per-chunk scatters; contiguous
    // chunks of the range order keep every tile's list in range order.
    w.sorted_rects.resize(V);
    const int64_t chunks = std::min<int64_t>(pool_->num_threads(), std::max<int64_t>(1, V / 4096));
    const int64_t len = (V + chunks - 1) / chunks;
    w.bin_counts.assign(static_cast<size_t>(chunks) * num_tiles, 0);
    pool_->ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
      for (int64_t c = c0; c < c1; ++c) {
        uint32_t* cnt = &w.bin_counts[c * num_tiles];
        // The gather first, in a loop of its own (independent misses overlap), then the counts.
        for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) w.sorted_rects[j] = w.rects[w.ids[j]];
        for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) {
          const Rect r = w.sorted_rects[j];
          for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) ++cnt[ty * tiles_x + tx];
        }
      }
    });
    w.tile_offsets.resize(num_tiles + 1);
    uint32_t sum = 0;
    for (int t = 0; t < num_tiles; ++t) {
      w.tile_offsets[t] = sum;
      for (int64_t c = 0; c < chunks; ++c) {
        uint32_t& v = w.bin_counts[c * num_tiles + t];
        const uint32_t cnt = v;
        v = sum;
        sum += cnt;
      }
    }
    w.tile_offsets[num_tiles] = sum;
    w.tile_ids.resize(sum);
    pool_->ParallelFor(chunks, 1, [&](int64_t c0, int64_t c1, int) {
      for (int64_t c = c0; c < c1; ++c) {
        uint32_t* cursor = &w.bin_counts[c * num_tiles];
        for (int64_t j = c * len; j < std::min(V, (c + 1) * len); ++j) {
          const uint32_t id = w.ids[j];
          const Rect r = w.sorted_rects[j];
          for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) w.tile_ids[cursor[ty * tiles_x + tx]++] = id;
        }
      }
    });
  }
  const auto t2 = std::chrono::steady_clock::now();

  // ---- Blend, one tile per task; signed T (negative: done) lands in alpha first ----
  const size_t P = static_cast<size_t>(B) * W;
  out->beams = B;
  out->columns = W;
  out->range.resize(P);
  out->intensity.resize(P);
  out->alpha.resize(P);
  out->range_sum.resize(P);
  out->intensity_sum.resize(P);
  const lidar::LidarBlendArgs bargs{w.splats.data(), w.tile_offsets.data(), w.tile_ids.data(), B, W, tiles_x,
                                    out->alpha.data(), out->range_sum.data(), out->intensity_sum.data()};
  pool_->ParallelFor(num_tiles, 1, [&](int64_t tb, int64_t te, int) { blend(bargs, tb, te); });
  // Returns (deterministic threshold or a hashed Bernoulli draw) and the normalised images.
  pool_->ParallelFor(B, 1, [&](int64_t b0, int64_t b1, int) {
    for (size_t pix = static_cast<size_t>(b0) * W; pix < static_cast<size_t>(b1) * W; ++pix) {
      const float a = 1.0f - std::fabs(out->alpha[pix]);
      out->alpha[pix] = a;
      bool ret;
      if (options.sample_drop) {
        const uint64_t h = SplitMix64(options.seed ^ SplitMix64(pix + 1));
        ret = static_cast<float>((h >> 40) * (1.0 / 16777216.0)) < a;
      } else {
        ret = a >= options.return_alpha_threshold;
      }
      const bool valid = ret && a > 0.0f;
      out->range[pix] = valid ? out->range_sum[pix] / a : 0.0f;
      out->intensity[pix] = valid ? out->intensity_sum[pix] / a : 0.0f;
    }
  });
  const auto t3 = std::chrono::steady_clock::now();

  out->points = LidarPoints{};
  if (options.want_points) {
    LidarPoints& pts = out->points;
    const Eigen::Isometry3d T_out = options.point_frame == LidarRenderOptions::PointFrame::kEgo
                                        ? model.T_ego_from_lidar
                                        : Eigen::Isometry3d::Identity();
    for (int b = 0; b < B; ++b) {
      for (int c = 0; c < W; ++c) {
        const size_t pix = static_cast<size_t>(b) * W + c;
        if (out->range[pix] <= 0.0f) continue;
        pts.xyz.push_back((T_out * (model.RayDirection(b, c) * out->range[pix])).cast<float>());
        pts.intensity.push_back(out->intensity[pix]);
        pts.time_us.push_back(options.sweep_start_us + model.ColumnTimeOffsetUs(c));
        pts.beam.push_back(static_cast<uint16_t>(b));
        pts.column.push_back(static_cast<uint16_t>(c));
      }
    }
  }
  out->num_gaussians = n;
  out->num_visible = static_cast<size_t>(V);
  out->num_tile_instances = w.tile_ids.size();
  out->projection_ms = Ms(t0, t1);
  out->sort_ms = Ms(t1, t2);
  out->blend_ms = Ms(t2, t3);
  out->total_ms = Ms(t0, std::chrono::steady_clock::now());
  return absl::OkStatus();
}

void BinPointsToRangeImage(const LidarModel& model, const std::vector<Eigen::Vector3f>& points,
                           const std::vector<float>* reflectance, std::vector<float>* range,
                           std::vector<float>* intensity) {
  const int B = model.beams(), W = model.columns;
  range->assign(static_cast<size_t>(B) * W, 0.0f);
  if (intensity) intensity->assign(static_cast<size_t>(B) * W, 0.0f);
  for (size_t i = 0; i < points.size(); ++i) {
    const Eigen::Vector3d p = points[i].cast<double>();
    const double r = p.norm();
    if (!(r >= model.min_range_m && r <= model.max_range_m)) continue;
    const double rho = std::hypot(p.x(), p.y());
    const double beam = model.BeamCoordinate(std::atan2(p.z(), rho));
    const int b = static_cast<int>(std::lround(beam));
    if (b < 0 || b >= B) continue;
    int c = static_cast<int>(std::lround(model.ColumnCoordinate(std::atan2(p.y(), p.x()))));
    if (c >= W) c -= W;
    if (c < 0) c += W;
    const size_t pix = static_cast<size_t>(b) * W + c;
    float& cell = (*range)[pix];
    if (cell == 0.0f || r < cell) {
      cell = static_cast<float>(r);
      if (intensity && reflectance) (*intensity)[pix] = (*reflectance)[i];
    }
  }
}

}  // namespace streetsim
