#include "render/lidar/lidar_renderer.h"

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "render/common/projection_math.h"
#include "render/common/thread_pool.h"
#include "render/cpu/simd_dispatch.h"
#include "render/lidar/lidar_backward.h"
#include "render/lidar/lidar_kernels.h"
#include "render/lidar/lidar_reference.h"

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

// The scalar reference projection of Gaussians [begin, end) (lidar_reference.h in float).
void ProjectScalar(const lidar::LidarSoa& s, const lidar::RefProjectParams<float>& rp, const float* refl,
                   uint32_t* gauss_col, int64_t begin, int64_t end, lidar::LidarProjectOut* out) {
  lidar::GaussianParams<float> gp;
  for (int64_t i = begin; i < end; ++i) {
    lidar::GetGaussian(s, refl, i, &gp);
    const int col = lidar::PoseColumn(rp, gp.mean);
    LidarSplat sp;
    float half_w, half_h;
    if (!lidar::ProjectGaussianRef(rp, col, gp, &sp, &half_w, &half_h)) continue;
    gauss_col[i] = static_cast<uint32_t>(col);
    lidar::FillSplat(rp.columns, rp.beams, rp.tiles_x, rp.tiles_y, sp, half_w, half_h, static_cast<uint32_t>(i),
                     out);
  }
}

// The scalar reference blend of tiles [tb, te) (signed T: the renderer takes |T|).
void BlendScalar(const lidar::LidarBlendArgs& args, int64_t tb, int64_t te) {
  float T[kTile * kTile], D[kTile * kTile], I[kTile * kTile];
  for (int64_t tile = tb; tile < te; ++tile) {
    const int x0 = static_cast<int>(tile % args.tiles_x) * kTile, y0 = static_cast<int>(tile / args.tiles_x) * kTile;
    const int rows = std::min(kTile, args.beams - y0), cols = std::min(kTile, args.columns - x0);
    lidar::BlendTileRef(args.splats, args.tile_ids, args.tile_offsets[tile], args.tile_offsets[tile + 1], x0, y0,
                        rows, cols, T, D, I, static_cast<int32_t*>(nullptr));
    for (int r = 0; r < rows; ++r) {
      for (int c = 0; c < cols; ++c) {
        const size_t pix = static_cast<size_t>(y0 + r) * args.columns + x0 + c;
        args.T[pix] = T[r * kTile + c];
        args.range_sum[pix] = D[r * kTile + c];
        args.intensity_sum[pix] = I[r * kTile + c];
      }
    }
  }
}

using ProjectFn = void (*)(const lidar::LidarSoa&, const lidar::LidarProjectParams&, int64_t, int64_t,
                           lidar::LidarProjectOut*);
using BlendFn = void (*)(const lidar::LidarBlendArgs&, int64_t, int64_t);

}  // namespace


struct LidarRenderer::Work {
  bool uploaded = false;
  lidar::LidarSoa soa;
  std::vector<float> elev, slope;
  std::vector<double> pose_table;
  std::vector<float> pose_table_f;
  // Projection output: block b of kProjectBlock Gaussians writes its splats (and seam copies)
  // densely from 2 b kProjectBlock on (LidarProjectOut); block_counts[b] of them.
  std::vector<LidarSplat> splats;
  std::vector<Rect> rects;
  std::vector<uint32_t> splat_gauss, gauss_col;
  std::vector<uint32_t> block_keys, block_counts;
  std::vector<uint32_t> ids, keys;
  std::vector<uint32_t> tile_offsets, tile_ids;
  lidar::BinScratch bin;
  // Backward state (valid while backward_ready).
  bool backward_ready = false;
  LidarModel model;
  std::vector<float> reflectance;
  bool has_reflectance = false;
  bool rolling = false;
  LidarRenderOptions::Kernel kernel = LidarRenderOptions::Kernel::kSimd;
  lidar::LidarBackwardScratch<float> bwd_scratch;
  std::vector<float> bwd_splat_grads;
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
  w.backward_ready = false;
  if (absl::Status s = store.Validate(); !s.ok()) return s;
  if (store.size() > (1u << 30)) return absl::InvalidArgumentError("too many Gaussians for the LiDAR renderer");
  lidar::CopyToSoa(*pool_, store, &w.soa);
  w.uploaded = true;
  return absl::OkStatus();
}

absl::Status LidarRenderer::UpdateRows(const GaussianStore& store, const ParamsChange& c) {
  Work& w = *work_;
  if (!w.uploaded || w.soa.n != store.size()) {
    return absl::InvalidArgumentError("LiDAR UpdateRows: no upload of this scene's size");
  }
  w.backward_ready = false;
  std::atomic<bool> bad{false};
  lidar::LidarSoa& s = w.soa;
  pool_->ParallelFor(static_cast<int64_t>(c.num_rows), 4096, [&](int64_t b, int64_t e, int) {
    bool local_bad = false;
    for (int64_t r = b; r < e; ++r) {
      const size_t i = c.rows[r];
      if (i >= s.n) {
        local_bad = true;
        continue;
      }
      if (c.means) {
        const float* m = &store.means[i * 3];
        s.mx[i] = m[0], s.my[i] = m[1], s.mz[i] = m[2];
        local_bad |= !std::isfinite(m[0]) || !std::isfinite(m[1]) || !std::isfinite(m[2]);
      }
      if (c.log_scales) {
        const float* l = &store.log_scales[i * 3];
        s.ls0[i] = l[0], s.ls1[i] = l[1], s.ls2[i] = l[2];
        local_bad |= !std::isfinite(l[0]) || !std::isfinite(l[1]) || !std::isfinite(l[2]);
      }
      if (c.rotations) {
        const float* q = &store.rotations[i * 4];
        s.qw[i] = q[0], s.qx[i] = q[1], s.qy[i] = q[2], s.qz[i] = q[3];
        const float q2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
        local_bad |= !std::isfinite(q2) || q2 == 0;
      }
      if (c.opacity) {
        s.opacity_logit[i] = store.opacity_logits[i];
        local_bad |= !std::isfinite(store.opacity_logits[i]);
      }
    }
    if (local_bad) bad.store(true, std::memory_order_relaxed);
  });
  if (bad.load()) {
    w.uploaded = false;
    return absl::InvalidArgumentError("LiDAR UpdateRows: a changed value is not finite or a row is out of range");
  }
  return absl::OkStatus();
}

absl::Status LidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                   const Eigen::Isometry3d& T_world_from_lidar,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  return Render(store, model, LidarSweepPose::Static(T_world_from_lidar), options, out);
}

absl::Status LidarRenderer::Render(const GaussianStore& store, const LidarModel& model,
                                   const LidarSweepPose& sweep, const LidarRenderOptions& options,
                                   LidarRenderOutput* out) {
  if (absl::Status s = Upload(store); !s.ok()) return s;
  return Render(model, sweep, options, out);
}

absl::Status LidarRenderer::Render(const LidarModel& model, const Eigen::Isometry3d& T_world_from_lidar,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  return Render(model, LidarSweepPose::Static(T_world_from_lidar), options, out);
}

absl::Status LidarRenderer::Render(const LidarModel& model, const LidarSweepPose& sweep,
                                   const LidarRenderOptions& options, LidarRenderOutput* out) {
  const auto t0 = std::chrono::steady_clock::now();
  Work& w = *work_;
  w.backward_ready = false;
  if (!w.uploaded) return absl::InvalidArgumentError("LidarRenderer: no scene uploaded");
  if (absl::Status s = model.Validate(); !s.ok()) return s;
  if (absl::Status s = ValidateSweepPose(sweep); !s.ok()) return s;
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

  // ---- Projection (rolling sweep: each column's pose, in double, then float) ----
  ColumnPoseTable(sweep, W, &w.pose_table);
  w.pose_table_f.assign(w.pose_table.begin(), w.pose_table.end());
  const bool rolling = !sweep.is_static();
  lidar::LidarProjectParams params;
  const float* mid = w.pose_table_f.data() + static_cast<size_t>(W / 2) * lidar::kPoseStride;
  std::copy(mid, mid + 9, params.R);
  std::copy(mid + 9, mid + 12, params.t);
  params.pose_table = w.pose_table_f.data();
  params.rolling = rolling;
  w.gauss_col.resize(n);
  params.gauss_col = w.gauss_col.data();
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
  lidar::RefProjectParams<float> rp;
  rp.model = &model;
  rp.pose_table = w.pose_table_f.data();
  rp.rolling = rolling;
  rp.near_m = params.near_m;
  rp.far_m = params.far_m;
  rp.cols_per_rad = params.cols_per_rad;
  rp.columns = W;
  rp.beams = B;
  rp.tiles_x = tiles_x;
  rp.tiles_y = tiles_y;
  constexpr int64_t kProjectBlock = 4096;
  const int64_t blocks = (static_cast<int64_t>(n) + kProjectBlock - 1) / kProjectBlock;
  w.splats.resize(2 * n);
  w.rects.resize(2 * n);
  w.block_keys.resize(2 * n);
  w.splat_gauss.resize(2 * n);
  w.block_counts.assign(blocks + 1, 0);
  pool_->ParallelFor(blocks, 1, [&](int64_t b0, int64_t b1, int) {
    for (int64_t blk = b0; blk < b1; ++blk) {
      const int64_t begin = blk * kProjectBlock, end = std::min<int64_t>(static_cast<int64_t>(n), begin + kProjectBlock);
      const size_t base = static_cast<size_t>(2 * begin);
      lidar::LidarProjectOut pout{w.splats.data() + base, w.rects.data() + base, w.block_keys.data() + base,
                                  w.splat_gauss.data() + base, 0};
      if (simd) {
        project_simd(w.soa, params, begin, end, &pout);
      } else {
        ProjectScalar(w.soa, rp, params.reflectance, w.gauss_col.data(), begin, end, &pout);
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
  lidar::SortAndBin(*pool_, &w.keys, &w.ids, w.rects.data(), tiles_x, tiles_y, &w.bin, &w.tile_offsets,
                    &w.tile_ids);
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

  FillLidarPoints(model, options, out);
  if (options.keep_for_backward) {
    w.model = model;
    w.has_reflectance = options.reflectance != nullptr;
    if (w.has_reflectance) w.reflectance = *options.reflectance;
    w.rolling = rolling;
    w.kernel = options.kernel;
    w.backward_ready = true;
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

// Points: range along the pixel's ray in the frame of its column's pose (that column's time).
void FillLidarPoints(const LidarModel& model, const LidarRenderOptions& options, LidarRenderOutput* out) {
  out->points = LidarPoints{};
  if (!options.want_points) return;
  LidarPoints& pts = out->points;
  const int B = model.beams(), W = model.columns;
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

absl::Status LidarRenderer::Backward(const LidarUpstreamGrads& upstream, LidarGaussianGrads* grads,
                                     bool deterministic) {
  Work& w = *work_;
  if (!w.backward_ready) {
    return absl::FailedPreconditionError(
        "LidarRenderer::Backward needs a Render with keep_for_backward (and no Upload since)");
  }
  const LidarModel& model = w.model;
  const int B = model.beams(), W = model.columns;
  lidar::LidarBackwardView<float> view;
  view.splats = w.splats.data();
  view.splat_gauss = w.splat_gauss.data();
  view.tile_offsets = w.tile_offsets.data();
  view.tile_ids = w.tile_ids.data();
  view.beams = B;
  view.columns = W;
  view.tiles_x = (W + kTile - 1) / kTile;
  view.tiles_y = (B + kTile - 1) / kTile;
  view.num_gaussians = w.soa.n;
  // The forward's kind: the scalar reference's backward after a kScalar forward, else the
  // vectorised one (each replays its own forward's arithmetic).
  if (w.kernel == LidarRenderOptions::Kernel::kScalar) {
    lidar::BlendBackward(*pool_, view, upstream, deterministic, &w.bwd_scratch, &w.bwd_splat_grads);
  } else {
    lidar::BlendBackwardVectorised(*pool_, view, upstream, w.kernel == LidarRenderOptions::Kernel::kSimdAvx2,
                                   deterministic, &w.bwd_scratch, &w.bwd_splat_grads);
  }
  lidar::RefProjectParams<float> rp;
  rp.model = &model;
  rp.pose_table = w.pose_table_f.data();
  rp.rolling = w.rolling;
  rp.near_m = std::max(kNearM, static_cast<float>(model.min_range_m));
  rp.far_m = static_cast<float>(model.max_range_m);
  rp.cols_per_rad = static_cast<float>(W / (2 * M_PI));
  rp.columns = W;
  rp.beams = B;
  rp.tiles_x = view.tiles_x;
  rp.tiles_y = view.tiles_y;
  lidar::ProjectBackward(*pool_, rp, w.soa, w.has_reflectance ? w.reflectance.data() : nullptr,
                         w.gauss_col.data(), w.bwd_splat_grads, grads);
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
