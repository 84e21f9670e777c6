#include "render/lidar/lidar_renderer.h"

#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "render/common/projection_math.h"
#include "render/common/thread_pool.h"

namespace streetsim {
namespace {

constexpr int kTile = 16;
constexpr float kLowPassPx = 0.3f;
constexpr float kMinAlpha = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.99f;
constexpr float kMinTransmittance = 1e-4f;
constexpr float kNearM = 0.2f;

// What the blender reads per splat.
struct LidarSplat {
  float x, y;      // column, beam coordinates of the mean
  float a, b, c;   // conic: power = -0.5 (a dx^2 + c dy^2) - b dx dy
  float opacity;
  float range;     // |mean| in the sensor frame, metres
  float refl;
  float half_w, half_h;  // tile box: the 3-sigma square intersected with the opacity box
  float op_w, op_h;      // opacity box half extents (px): outside it opacity * G < 1/255
};

struct Rect {
  int x0, y0, x1, y1;  // tiles, [x0, x1) x [y0, y1)
  int count() const { return (x1 - x0) * (y1 - y0); }
};

double Ms(std::chrono::steady_clock::time_point a, std::chrono::steady_clock::time_point b) {
  return std::chrono::duration<double, std::milli>(b - a).count();
}

uint64_t SplitMix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

// Stable LSD radix sort of (key, value) pairs by 32-bit key, 11-bit digits; constant digits skipped.
void RadixSortPairs(std::vector<uint32_t>* keys, std::vector<uint32_t>* values,
                    std::vector<uint32_t>* sk, std::vector<uint32_t>* sv) {
  constexpr int kBits = 11;
  constexpr uint32_t kBins = 1u << kBits;
  const size_t n = keys->size();
  sk->resize(n);
  sv->resize(n);
  std::vector<uint32_t> hist(3 * kBins, 0);
  for (size_t i = 0; i < n; ++i) {
    const uint32_t k = (*keys)[i];
    ++hist[k & (kBins - 1)];
    ++hist[kBins + ((k >> kBits) & (kBins - 1))];
    ++hist[2 * kBins + (k >> (2 * kBits))];
  }
  for (int pass = 0; pass < 3; ++pass) {
    uint32_t* h = &hist[pass * kBins];
    if (std::any_of(h, h + kBins, [n](uint32_t c) { return c == n; })) continue;
    uint32_t sum = 0;
    for (uint32_t b = 0; b < kBins; ++b) {
      const uint32_t c = h[b];
      h[b] = sum;
      sum += c;
    }
    const int shift = pass * kBits;
    for (size_t i = 0; i < n; ++i) {
      const uint32_t k = (*keys)[i];
      const uint32_t pos = h[(k >> shift) & (kBins - 1)]++;
      (*sk)[pos] = k;
      (*sv)[pos] = (*values)[i];
    }
    keys->swap(*sk);
    values->swap(*sv);
  }
}

}  // namespace

struct LidarRenderer::Work {
  // Indexed by entry: entry i < N is Gaussian i, entry N + i its copy shifted by one turn in
  // azimuth (present when the splat crosses the seam behind the sensor).
  std::vector<LidarSplat> splats;
  std::vector<Rect> rects;
  std::vector<uint8_t> visible;
  std::vector<uint32_t> ids, keys, scratch_keys, scratch_ids;
  std::vector<uint32_t> tile_offsets, tile_ids;
};

LidarRenderer::LidarRenderer(int num_threads)
    : pool_(std::make_unique<ThreadPool>(num_threads)), work_(std::make_unique<Work>()) {}
LidarRenderer::~LidarRenderer() = default;

absl::Status LidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                   const Eigen::Isometry3d& T_world_from_lidar,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  const auto t0 = std::chrono::steady_clock::now();
  if (absl::Status s = model.Validate(); !s.ok()) return s;
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  {
    const Eigen::Matrix3d R = T_world_from_lidar.linear();
    if (!T_world_from_lidar.matrix().allFinite() ||
        !(R.transpose() * R).isApprox(Eigen::Matrix3d::Identity(), 1e-6) || R.determinant() < 0) {
      return absl::InvalidArgumentError("T_world_from_lidar must be a finite rigid transform");
    }
  }
  const size_t n = store.size();
  if (options.reflectance && options.reflectance->size() != n) {
    return absl::InvalidArgumentError(absl::StrCat("reflectance has ", options.reflectance->size(),
                                                   " values for ", n, " Gaussians"));
  }
  if (n > (1u << 30)) return absl::InvalidArgumentError("too many Gaussians for the LiDAR renderer");

  const int B = model.beams(), W = model.columns;
  const int tiles_x = (W + kTile - 1) / kTile, tiles_y = (B + kTile - 1) / kTile;
  const int num_tiles = tiles_x * tiles_y;
  Work& w = *work_;

  // ---- Projection ----
  const Eigen::Isometry3d T_lidar_from_world = T_world_from_lidar.inverse();
  float Rlw[9], tlw[3];
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) Rlw[r * 3 + k] = static_cast<float>(T_lidar_from_world.linear()(r, k));
    tlw[r] = static_cast<float>(T_lidar_from_world.translation()[r]);
  }
  const float near_m = std::max(kNearM, static_cast<float>(model.min_range_m));
  const float far_m = static_cast<float>(model.max_range_m);
  const double cols_per_rad = W / (2 * M_PI);
  w.splats.resize(2 * n);
  w.rects.resize(2 * n);
  w.visible.assign(2 * n, 0);

  pool_->ParallelFor(static_cast<int64_t>(n), 4096, [&](int64_t begin, int64_t end, int) {
    for (int64_t i = begin; i < end; ++i) {
      const float* m = &store.means[i * 3];
      const float px = Rlw[0] * m[0] + Rlw[1] * m[1] + Rlw[2] * m[2] + tlw[0];
      const float py = Rlw[3] * m[0] + Rlw[4] * m[1] + Rlw[5] * m[2] + tlw[1];
      const float pz = Rlw[6] * m[0] + Rlw[7] * m[1] + Rlw[8] * m[2] + tlw[2];
      const float rho2 = px * px + py * py;
      const float r2 = rho2 + pz * pz;
      const float range = std::sqrt(r2);
      if (!(range > near_m) || !(range < far_m)) continue;  // also rejects NaN
      const float rho = std::sqrt(rho2);
      if (!(rho > 1e-3f * range)) continue;  // straight up/down: no beam looks there
      const float opacity = 1.0f / (1.0f + std::exp(-store.opacity_logits[i]));
      if (!(opacity * 255.0f > 1.0f)) continue;

      // Sigma = R S S^T R^T (world frame).
      float R[9];
      projection::QuatToRotation(&store.rotations[i * 4], R);
      const float* ls = &store.log_scales[i * 3];
      const float s[3] = {std::exp(std::clamp(ls[0], -30.0f, 30.0f)), std::exp(std::clamp(ls[1], -30.0f, 30.0f)),
                          std::exp(std::clamp(ls[2], -30.0f, 30.0f))};
      float M[9];
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) M[r * 3 + c] = R[r * 3 + c] * s[c];
      float Sg[6];
      Sg[0] = M[0] * M[0] + M[1] * M[1] + M[2] * M[2];
      Sg[1] = M[0] * M[3] + M[1] * M[4] + M[2] * M[5];
      Sg[2] = M[0] * M[6] + M[1] * M[7] + M[2] * M[8];
      Sg[3] = M[3] * M[3] + M[4] * M[4] + M[5] * M[5];
      Sg[4] = M[3] * M[6] + M[4] * M[7] + M[5] * M[8];
      Sg[5] = M[6] * M[6] + M[7] * M[7] + M[8] * M[8];

      // Spherical projection and its Jacobian at the sensor-frame mean.
      //   u = (pi - atan2(y, x)) W / 2pi - 0.5:  du/dp = W/2pi (y, -x, 0) / rho^2
      //   v = beam(atan2(z, rho)):              dv/dp = beam'(el) (-x z / rho, -y z / rho, rho) / r^2
      const float elevation = std::atan2(pz, rho);
      double dbeam = 0;
      const float v = static_cast<float>(model.BeamCoordinate(elevation, &dbeam));
      const float u = static_cast<float>(model.ColumnCoordinate(std::atan2(py, px)));
      const float ku = static_cast<float>(cols_per_rad) / rho2;
      const float kv = static_cast<float>(dbeam) / r2;
      const float J0[3] = {ku * py, -ku * px, 0.0f};
      const float J1[3] = {-kv * px * pz / rho, -kv * py * pz / rho, kv * rho};
      // T = J W (2x3), W = R_lidar_from_world.
      float T0[3], T1[3];
      for (int k = 0; k < 3; ++k) {
        T0[k] = J0[0] * Rlw[k] + J0[1] * Rlw[3 + k] + J0[2] * Rlw[6 + k];
        T1[k] = J1[0] * Rlw[k] + J1[1] * Rlw[3 + k] + J1[2] * Rlw[6 + k];
      }
      auto sigma_times = [&](const float* a, float* o) {
        o[0] = Sg[0] * a[0] + Sg[1] * a[1] + Sg[2] * a[2];
        o[1] = Sg[1] * a[0] + Sg[3] * a[1] + Sg[4] * a[2];
        o[2] = Sg[2] * a[0] + Sg[4] * a[1] + Sg[5] * a[2];
      };
      float S0[3], S1[3];
      sigma_times(T0, S0);
      sigma_times(T1, S1);
      const float cxx = T0[0] * S0[0] + T0[1] * S0[1] + T0[2] * S0[2] + kLowPassPx;
      const float cxy = T0[0] * S1[0] + T0[1] * S1[1] + T0[2] * S1[2];
      const float cyy = T1[0] * S1[0] + T1[1] * S1[1] + T1[2] * S1[2] + kLowPassPx;
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
      sp.refl = options.reflectance ? std::clamp((*options.reflectance)[i], 0.0f, 1.0f) : 0.5f;
      // The 3-sigma square intersected with the opacity box (as the camera path).
      const float mid = 0.5f * (cxx + cyy);
      const float lambda_max = mid + std::sqrt(std::max(0.1f, mid * mid - det));
      const float radius = std::ceil(3.0f * std::sqrt(lambda_max));
      const float d2 = 2.0f * std::log(opacity * 255.0f);
      sp.op_w = std::sqrt(d2 * cxx);
      sp.op_h = std::sqrt(d2 * cyy);
      sp.half_w = std::min(radius, sp.op_w);
      sp.half_h = std::min(radius, sp.op_h);
      if (!std::isfinite(sp.x) || !std::isfinite(sp.y) || !std::isfinite(sp.half_w) ||
          !std::isfinite(sp.half_h)) {
        continue;
      }
      auto rect_of = [&](float x) {
        auto clampi = [](float t, int hi) { return static_cast<int>(std::min(std::max(t, 0.0f), static_cast<float>(hi))); };
        // Pixel c samples coordinate c; tile t holds pixels [16 t, 16 t + 16) (as the camera path).
        Rect r;
        r.x0 = clampi(std::floor((x - sp.half_w) / kTile), tiles_x);
        r.x1 = clampi(std::floor((x + sp.half_w) / kTile) + 1, tiles_x);
        r.y0 = clampi(std::floor((sp.y - sp.half_h) / kTile), tiles_y);
        r.y1 = clampi(std::floor((sp.y + sp.half_h) / kTile) + 1, tiles_y);
        if (r.x1 <= r.x0 || r.y1 <= r.y0) r = Rect{0, 0, 0, 0};
        return r;
      };
      // Rows beyond the image: nothing to draw.
      if (sp.y + sp.half_h < -0.5f || sp.y - sp.half_h > B - 0.5f) continue;
      const Rect r = rect_of(sp.x);
      if (r.count() > 0) {
        w.splats[i] = sp;
        w.rects[i] = r;
        w.visible[i] = 1;
      }
      // The seam behind the sensor: a splat reaching past either end of the columns is drawn
      // again one turn away (not when it spans more than half a turn: it would be drawn twice).
      if (sp.half_w < 0.5f * W) {
        float x2 = 0;
        bool wrap = false;
        if (sp.x - sp.half_w < -0.5f) { x2 = sp.x + W; wrap = true; }
        if (sp.x + sp.half_w > W - 0.5f) { x2 = sp.x - W; wrap = true; }
        if (wrap) {
          LidarSplat sp2 = sp;
          sp2.x = x2;
          const Rect r2 = rect_of(x2);
          if (r2.count() > 0) {
            w.splats[n + i] = sp2;
            w.rects[n + i] = r2;
            w.visible[n + i] = 1;
          }
        }
      }
    }
  });
  w.ids.clear();
  for (size_t e = 0; e < 2 * n; ++e) {
    if (w.visible[e]) w.ids.push_back(static_cast<uint32_t>(e));
  }
  const auto t1 = std::chrono::steady_clock::now();

  // ---- Sort by range (ties: entry index), bin into tiles ----
  const size_t V = w.ids.size();
  w.keys.resize(V);
  for (size_t j = 0; j < V; ++j) w.keys[j] = std::bit_cast<uint32_t>(w.splats[w.ids[j]].range);
  RadixSortPairs(&w.keys, &w.ids, &w.scratch_keys, &w.scratch_ids);
  w.tile_offsets.assign(num_tiles + 1, 0);
  for (size_t j = 0; j < V; ++j) {
    const Rect& r = w.rects[w.ids[j]];
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) ++w.tile_offsets[ty * tiles_x + tx + 1];
  }
  for (int t = 0; t < num_tiles; ++t) w.tile_offsets[t + 1] += w.tile_offsets[t];
  w.tile_ids.resize(w.tile_offsets[num_tiles]);
  {
    std::vector<uint32_t> cursor(w.tile_offsets.begin(), w.tile_offsets.end() - 1);
    for (size_t j = 0; j < V; ++j) {
      const uint32_t id = w.ids[j];
      const Rect& r = w.rects[id];
      for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) w.tile_ids[cursor[ty * tiles_x + tx]++] = id;
    }
  }
  const auto t2 = std::chrono::steady_clock::now();

  // ---- Blend, one tile per task ----
  const size_t P = static_cast<size_t>(B) * W;
  out->beams = B;
  out->columns = W;
  out->range.assign(P, 0.0f);
  out->intensity.assign(P, 0.0f);
  out->alpha.assign(P, 0.0f);
  out->range_sum.assign(P, 0.0f);
  out->intensity_sum.assign(P, 0.0f);
  pool_->ParallelFor(num_tiles, 1, [&](int64_t tb, int64_t te, int) {
    float T[kTile * kTile], D[kTile * kTile], I[kTile * kTile];
    for (int64_t tile = tb; tile < te; ++tile) {
      const int tx = static_cast<int>(tile % tiles_x), ty = static_cast<int>(tile / tiles_x);
      const int x0 = tx * kTile, y0 = ty * kTile;
      const int rows = std::min(kTile, B - y0), cols = std::min(kTile, W - x0);
      int live = rows * cols;
      for (int p = 0; p < kTile * kTile; ++p) {
        T[p] = 1.0f;
        D[p] = I[p] = 0.0f;
      }
      for (uint32_t j = w.tile_offsets[tile]; j < w.tile_offsets[tile + 1] && live > 0; ++j) {
        const LidarSplat s = w.splats[w.tile_ids[j]];
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
          const float a = 1.0f - std::fabs(T[p]);
          out->alpha[pix] = a;
          out->range_sum[pix] = D[p];
          out->intensity_sum[pix] = I[p];
          bool ret;
          if (options.sample_drop) {
            const uint64_t h = SplitMix64(options.seed ^ SplitMix64(pix + 1));
            ret = static_cast<float>((h >> 40) * (1.0 / 16777216.0)) < a;
          } else {
            ret = a >= options.return_alpha_threshold;
          }
          if (ret && a > 0.0f) {
            out->range[pix] = D[p] / a;
            out->intensity[pix] = I[p] / a;
          }
        }
      }
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
  out->num_visible = V;
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
