#include "scene/field/field_eval.h"

#include <algorithm>
#include <chrono>
#include <vector>

#include <Eigen/Core>

#include "scene/field/hexplane_kernels.h"

namespace streetsim::field {

namespace {

using internal::MakePlaneTaps;
using internal::MakeTap;
using internal::PlaneTaps;
using internal::Tap;

constexpr int64_t kRowsPerChunk = 256;     // rows per thread task: GEMMs of 256 x {128, 64}
constexpr size_t kBackwardBlock = 2048;    // rows whose plane gradients are scattered together
// Backward rows per task: small enough that the texels a chunk sampled are still in L2 when its
// position gradient reads them again (64 vs 128: 1.94 vs 2.23 s CPU, 300k random, one thread).
constexpr int64_t kBackwardRowsPerChunk = 64;
constexpr int kMaxChannels = 256;          // FieldConfig::Validate's bound (backward stack scratch)
constexpr int64_t kPrefetchRows = 16;      // sampling: prefetch the taps of the row this far ahead

template <typename T>
using Mat = Eigen::Matrix<T, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
template <typename T>
using RowVec = Eigen::Matrix<T, 1, Eigen::Dynamic>;

template <typename T>
struct ThreadScratch {
  Mat<T> F, H, A, P, S, dP, dS, dA, dF;
  std::vector<T> mlp_grad;  // [layout.total - layout.grid_size]
  std::vector<Tap<T>> taps;  // per row of the chunk: x, y, z taps of one level
};

template <typename T>
struct WorkspaceT {
  std::vector<ThreadScratch<T>> threads;
  std::vector<T> samples;          // [block * planes * C]: samples, then dL/d(sample) in place
  std::vector<PlaneTaps<T>> taps;  // [block * planes]
  void Reserve(int num_threads) {
    if (static_cast<int>(threads.size()) < num_threads) threads.resize(num_threads);
  }
};

// Positions to plane coordinates: p = a * x + b, the spec's reversed map
// p = 1 - 2 (x - min) / (max - min).
template <typename T>
struct Normaliser {
  T a[3], b[3];
  T time;
  explicit Normaliser(const FieldQuery& q) {
    for (int k = 0; k < 3; ++k) {
      const double ext = q.aabb_max[k] - q.aabb_min[k];
      a[k] = static_cast<T>(-2.0 / ext);
      b[k] = static_cast<T>(1.0 + 2.0 * q.aabb_min[k] / ext);
    }
    time = static_cast<T>(q.time_coord);
  }
};

// The features of a chunk of Gaussians, F [rows x D] row-major. Plane-major: one plane at a time
// over every row of the chunk, so that the rows' (independent) cache misses on that plane overlap
// instead of queueing behind each Gaussian's chain of 24 samples. With taps_out / samples_out
// (backward), also keeps every plane's taps and sample per row, plane-major ([slot * slot_rows +
// row]): the backward's scatter then reads each plane's rows as one contiguous run (row-major, a
// 3 KiB stride between a plane's rows, stalled it on those loads most of its time).
// `planes`: which planes of a level are sampled (bit c: plane c); F starts from `init` (rows
// [b, e) of it) or 1.
constexpr unsigned kAllPlanes = 0x3f, kSpatialPlanes = 0x0b, kTimePlanes = 0x34;  // {xy,xz,yz}, {xt,yt,zt}

template <typename T>
inline void FeatureChunk(const FieldLayout& L, const T* params, const Normaliser<T>& nm, const T* means,
                         const uint32_t* rows, int64_t b, int64_t e, T* F, PlaneTaps<T>* taps_out,
                         T* samples_out, size_t slot_rows, std::vector<Tap<T>>& tap_scratch,
                         unsigned planes = kAllPlanes, const T* init = nullptr) {
  const int C = L.channels;
  const int D = L.feature_dim();
  const int64_t B = e - b;
  if (init) {
    std::copy(init + b * D, init + e * D, F);
  } else {
    std::fill(F, F + B * D, T(1));
  }
  tap_scratch.resize(B * 3);
  const Tap<T> tt = MakeTap(nm.time, L.time_resolution);
  for (int l = 0; l < L.num_levels; ++l) {
    const int R = L.level_resolution[l];
    for (int64_t r = 0; r < B; ++r) {
      const size_t g = rows ? rows[b + r] : static_cast<size_t>(b + r);
      for (int k = 0; k < 3; ++k) tap_scratch[r * 3 + k] = MakeTap(nm.a[k] * means[g * 3 + k] + nm.b[k], R);
    }
    for (int c = 0; c < kPlanesPerLevel; ++c) {
      if (!(planes & (1u << c))) continue;
      const PlaneInfo& pi = L.planes[l * kPlanesPerLevel + c];
      const T* plane = params + pi.offset;
      const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
      const int slot = l * kPlanesPerLevel + c;
      for (int64_t r = 0; r < B; ++r) {
        if (r + kPrefetchRows < B) {
          // The taps a few rows ahead: their cache misses overlap with this row's work.
          const int64_t q = r + kPrefetchRows;
          const PlaneTaps<T> ahead =
              MakePlaneTaps(tap_scratch[q * 3 + cu], cv == 3 ? tt : tap_scratch[q * 3 + cv], pi.width, C);
          const char* a = reinterpret_cast<const char*>(plane + ahead.off00);
          const char* a1 = reinterpret_cast<const char*>(plane + ahead.off00 + ahead.row);
          for (size_t o = 0; o < 2 * C * sizeof(T); o += 64) {
            __builtin_prefetch(a + o);
            __builtin_prefetch(a1 + o);
          }
        }
        const Tap<T>& tu = tap_scratch[r * 3 + cu];
        const Tap<T>& tv = cv == 3 ? tt : tap_scratch[r * 3 + cv];
        const PlaneTaps<T> pt = MakePlaneTaps(tu, tv, pi.width, C);
        T* f = F + r * D + l * C;
        if (samples_out) {
          const size_t row = static_cast<size_t>(b + r);  // rows of the backward block
          T* s = samples_out + (slot * slot_rows + row) * C;
          internal::SamplePlane(plane, pt, C, s);
          for (int k = 0; k < C; ++k) f[k] *= s[k];
          taps_out[slot * slot_rows + row] = pt;
        } else {
          internal::SampleMulPlane(plane, pt, C, f);
        }
      }
    }
  }
}

// Backward of FeatureChunk for one Gaussian: turns the kept samples into dL/d(sample) (in place)
// and returns dL/d(xyz) through the sampling coordinates. taps / samples: the row's first slot;
// slot s is slot_rows entries further on (FeatureChunk's plane-major layout).
template <typename T>
inline void FeatureRowBackward(const FieldLayout& L, const T* params, const Normaliser<T>& nm, const T* xyz,
                               const T* dF, const PlaneTaps<T>* taps, T* samples, size_t slot_rows, T* d_xyz) {
  const int C = L.channels;
  T p[3];
  for (int k = 0; k < 3; ++k) p[k] = nm.a[k] * xyz[k] + nm.b[k];
  T dp[3] = {0, 0, 0};
  T pre[kMaxChannels], suf[kPlanesPerLevel][kMaxChannels];
  for (int l = 0; l < L.num_levels; ++l) {
    const int R = L.level_resolution[l];
    const Tap<T> taps_xyz[3] = {MakeTap(p[0], R), MakeTap(p[1], R), MakeTap(p[2], R)};
    const size_t slot0 = static_cast<size_t>(l) * kPlanesPerLevel;
    auto sample = [&](int c) { return samples + (slot0 + c) * slot_rows * C; };
    // Products of all other planes: prefix (times dF) and suffix products, no division (samples
    // can be exactly 0).
    for (int k = 0; k < C; ++k) suf[kPlanesPerLevel - 1][k] = T(1);
    for (int c = kPlanesPerLevel - 2; c >= 0; --c) {
      const T* sn = sample(c + 1);
      for (int k = 0; k < C; ++k) suf[c][k] = suf[c + 1][k] * sn[k];
    }
    for (int k = 0; k < C; ++k) pre[k] = dF[l * C + k];
    for (int c = 0; c < kPlanesPerLevel; ++c) {
      T* sc = sample(c);
      for (int k = 0; k < C; ++k) {
        const T g = pre[k] * suf[c][k];
        pre[k] *= sc[k];
        sc[k] = g;
      }
      const int cu = kPlaneCoords[c][0], cv = kPlaneCoords[c][1];
      const PlaneInfo& pi = L.planes[l * kPlanesPerLevel + c];
      const PlaneTaps<T>& pt = taps[(slot0 + c) * slot_rows];
      const T wu = taps_xyz[cu].w;
      const T wv = cv == 3 ? MakeTap(nm.time, L.time_resolution).w : taps_xyz[cv].w;
      T du = 0, dv = 0;
      internal::SampleCoordGrad(params + pi.offset, pt, wu, wv, C, sc, &du, &dv);
      dp[cu] += du * taps_xyz[cu].dpx_dp;
      if (cv != 3) dp[cv] += dv * taps_xyz[cv].dpx_dp;  // time is not a parameter
    }
  }
  for (int k = 0; k < 3; ++k) d_xyz[k] += dp[k] * nm.a[k];
}

template <typename T>
auto Weight(const FieldLayout&, const T* params, const DenseInfo& d) {
  return Eigen::Map<const Mat<T>>(params + d.w_offset, d.out, d.in);
}
template <typename T>
auto Bias(const T* params, const DenseInfo& d) {
  return Eigen::Map<const RowVec<T>>(params + d.b_offset, d.out);
}

// MLP forward on the chunk's features sc.F; keeps the activations for the backward.
template <typename T>
void MlpForward(const FieldLayout& L, const T* params, ThreadScratch<T>& sc, bool want_dsh, T* dx, T* dsh) {
  const Eigen::Index B = sc.F.rows();
  sc.H.noalias() = sc.F * Weight(L, params, L.trunk).transpose();
  sc.H.rowwise() += Bias(params, L.trunk);
  sc.A = sc.H.cwiseMax(T(0));
  sc.P.noalias() = sc.A * Weight(L, params, L.pos1).transpose();
  sc.P.rowwise() += Bias(params, L.pos1);
  sc.P = sc.P.cwiseMax(T(0));
  if (dx) {
    Eigen::Map<Mat<T>> out(dx, B, 3);
    out.noalias() = sc.P * Weight(L, params, L.pos2).transpose();
    out.rowwise() += Bias(params, L.pos2);
  }
  if (want_dsh) {
    sc.S.noalias() = sc.A * Weight(L, params, L.sh1).transpose();
    sc.S.rowwise() += Bias(params, L.sh1);
    sc.S = sc.S.cwiseMax(T(0));
    if (dsh) {
      Eigen::Map<Mat<T>> out(dsh, B, kShOutputs);
      out.noalias() = sc.S * Weight(L, params, L.sh2).transpose();
      out.rowwise() += Bias(params, L.sh2);
    }
  }
}

// dst[j] += sum of column j of the row-major rows x cols matrix m, rows in order. Not
// `Map(dst) += m.colwise().sum()`: Eigen assigns into an unaligned Map by peeling up to the
// destination's runtime alignment, and the peeled columns are summed in another order than the
// vectorised ones, so a bias gradient's last bit depended on where malloc had put mlp_grad
// (mod 32 bytes), which differs between processes (docs/training.md "Reproducibility").
template <typename T>
inline void AddColumnSums(const T* __restrict m, Eigen::Index rows, Eigen::Index cols, T* __restrict dst) {
  for (Eigen::Index r = 0; r < rows; ++r) {
    const T* __restrict row = m + r * cols;
    for (Eigen::Index j = 0; j < cols; ++j) dst[j] += row[j];
  }
}

// Accumulates the MLP parameter gradients into sc.mlp_grad and leaves dL/dF in sc.dF.
template <typename T>
void MlpBackward(const FieldLayout& L, const T* params, ThreadScratch<T>& sc, const T* g_dx, const T* g_dsh) {
  const Eigen::Index B = sc.F.rows();
  T* G = sc.mlp_grad.data() - L.grid_size;  // indexable by the layout's offsets
  auto dW = [&](const DenseInfo& d) { return Eigen::Map<Mat<T>>(G + d.w_offset, d.out, d.in); };
  sc.dA.setZero(B, L.width);
  if (g_dx) {
    Eigen::Map<const Mat<T>> gdx(g_dx, B, 3);
    dW(L.pos2).noalias() += gdx.transpose() * sc.P;
    AddColumnSums(g_dx, B, 3, G + L.pos2.b_offset);
    sc.dP.noalias() = gdx * Weight(L, params, L.pos2);
    sc.dP.array() *= (sc.P.array() > T(0)).template cast<T>();
    dW(L.pos1).noalias() += sc.dP.transpose() * sc.A;
    AddColumnSums(sc.dP.data(), B, sc.dP.cols(), G + L.pos1.b_offset);
    sc.dA.noalias() += sc.dP * Weight(L, params, L.pos1);
  }
  if (g_dsh) {
    Eigen::Map<const Mat<T>> gdsh(g_dsh, B, kShOutputs);
    dW(L.sh2).noalias() += gdsh.transpose() * sc.S;
    AddColumnSums(g_dsh, B, Eigen::Index{kShOutputs}, G + L.sh2.b_offset);
    sc.dS.noalias() = gdsh * Weight(L, params, L.sh2);
    sc.dS.array() *= (sc.S.array() > T(0)).template cast<T>();
    dW(L.sh1).noalias() += sc.dS.transpose() * sc.A;
    AddColumnSums(sc.dS.data(), B, sc.dS.cols(), G + L.sh1.b_offset);
    sc.dA.noalias() += sc.dS * Weight(L, params, L.sh1);
  }
  sc.dA.array() *= (sc.H.array() > T(0)).template cast<T>();  // now dL/dH
  dW(L.trunk).noalias() += sc.dA.transpose() * sc.F;
  AddColumnSums(sc.dA.data(), B, sc.dA.cols(), G + L.trunk.b_offset);
  sc.dF.noalias() = sc.dA * Weight(L, params, L.trunk);
}

// ParallelFor that hands fn at most `chunk` rows at a time: the pool gives a single thread the
// whole range in one call, and the chunk's scratch (features, activations) must stay in cache.
template <typename Fn>
void ForChunks(ThreadPool& pool, int64_t n, int64_t chunk, const Fn& fn) {
  pool.ParallelFor(n, chunk, [&](int64_t b, int64_t e, int tid) {
    for (int64_t c = b; c < e; c += chunk) fn(c, std::min(e, c + chunk), tid);
  });
}

template <typename T>
WorkspaceT<T>& Get(FieldWorkspace::Impl& impl);

}  // namespace

struct FieldWorkspace::Impl {
  WorkspaceT<float> f;
  WorkspaceT<double> d;
};
FieldWorkspace::FieldWorkspace() : impl_(std::make_unique<Impl>()) {}
FieldWorkspace::~FieldWorkspace() = default;

namespace {
template <>
WorkspaceT<float>& Get<float>(FieldWorkspace::Impl& impl) { return impl.f; }
template <>
WorkspaceT<double>& Get<double>(FieldWorkspace::Impl& impl) { return impl.d; }
}  // namespace

template <typename T>
void FieldForward(const FieldLayout& L, const T* params, const FieldQuery& query, const T* means,
                  const uint32_t* rows, size_t n, T* dx, T* dsh, ThreadPool& pool, FieldWorkspace& ws_outer) {
  WorkspaceT<T>& ws = Get<T>(ws_outer.impl());
  ws.Reserve(pool.num_threads());
  const Normaliser<T> nm(query);
  const int D = L.feature_dim();
  ForChunks(pool, static_cast<int64_t>(n), kRowsPerChunk, [&](int64_t b, int64_t e, int tid) {
    ThreadScratch<T>& sc = ws.threads[tid];
    sc.F.resize(e - b, D);
    FeatureChunk(L, params, nm, means, rows, b, e, sc.F.data(), static_cast<PlaneTaps<T>*>(nullptr),
                 static_cast<T*>(nullptr), 0, sc.taps);
    MlpForward(L, params, sc, dsh != nullptr, dx ? dx + b * 3 : nullptr, dsh ? dsh + b * kShOutputs : nullptr);
  });
}

template <typename T>
void SpatialFeatures(const FieldLayout& L, const T* params, const FieldQuery& query, const T* means,
                     const uint32_t* rows, size_t n, T* spatial, ThreadPool& pool) {
  const Normaliser<T> nm(query);
  const int D = L.feature_dim();
  ForChunks(pool, static_cast<int64_t>(n), kRowsPerChunk, [&](int64_t b, int64_t e, int) {
    std::vector<Tap<T>> taps;
    FeatureChunk(L, params, nm, means, rows, b, e, spatial + b * D, static_cast<PlaneTaps<T>*>(nullptr),
                 static_cast<T*>(nullptr), 0, taps, kSpatialPlanes);
  });
}

template <typename T>
void FieldForwardCached(const FieldLayout& L, const T* params, const FieldQuery& query, const T* means,
                        const uint32_t* rows, const T* spatial, size_t n, T* dx, T* dsh, ThreadPool& pool,
                        FieldWorkspace& ws_outer) {
  WorkspaceT<T>& ws = Get<T>(ws_outer.impl());
  ws.Reserve(pool.num_threads());
  const Normaliser<T> nm(query);
  const int D = L.feature_dim();
  ForChunks(pool, static_cast<int64_t>(n), kRowsPerChunk, [&](int64_t b, int64_t e, int tid) {
    ThreadScratch<T>& sc = ws.threads[tid];
    sc.F.resize(e - b, D);
    FeatureChunk(L, params, nm, means, rows, b, e, sc.F.data(), static_cast<PlaneTaps<T>*>(nullptr),
                 static_cast<T*>(nullptr), 0, sc.taps, kTimePlanes, spatial);
    MlpForward(L, params, sc, dsh != nullptr, dx ? dx + b * 3 : nullptr, dsh ? dsh + b * kShOutputs : nullptr);
  });
}

template <typename T>
void FieldBackward(const FieldLayout& L, const T* params, const FieldQuery& query, const T* means, size_t n,
                   const T* d_dx, const T* d_dsh, T* d_params, T* d_means, ThreadPool& pool,
                   FieldWorkspace& ws_outer) {
  if (L.channels > kMaxChannels) return;  // unreachable through DeformationField (validated configs)
  WorkspaceT<T>& ws = Get<T>(ws_outer.impl());
  const int nt = pool.num_threads();
  ws.Reserve(nt);
  const size_t mlp_size = L.total - L.grid_size;
  for (int t = 0; t < nt; ++t) ws.threads[t].mlp_grad.assign(mlp_size, T(0));
  const Normaliser<T> nm(query);
  const int D = L.feature_dim();
  const int C = L.channels;
  const int NP = L.num_levels * kPlanesPerLevel;
  const size_t block = std::min(kBackwardBlock, std::max<size_t>(n, 1));
  ws.samples.resize(block * NP * C);
  ws.taps.resize(block * NP);
  using Clock = std::chrono::steady_clock;
  double rows_ms = 0, scatter_ms = 0;
  for (size_t b0 = 0; b0 < n; b0 += block) {
    const size_t bn = std::min(block, n - b0);
    const auto t0 = Clock::now();
    ForChunks(pool, static_cast<int64_t>(bn), kBackwardRowsPerChunk, [&](int64_t b, int64_t e, int tid) {
      ThreadScratch<T>& sc = ws.threads[tid];
      sc.F.resize(e - b, D);
      FeatureChunk(L, params, nm, means + b0 * 3, static_cast<const uint32_t*>(nullptr), b, e, sc.F.data(),
                   ws.taps.data(), ws.samples.data(), block, sc.taps);
      MlpForward(L, params, sc, d_dsh != nullptr, static_cast<T*>(nullptr), static_cast<T*>(nullptr));
      MlpBackward(L, params, sc, d_dx ? d_dx + (b0 + b) * 3 : nullptr,
                  d_dsh ? d_dsh + (b0 + b) * kShOutputs : nullptr);
      T scratch_xyz[3];
      for (int64_t r = b; r < e; ++r) {
        T* dxyz = d_means ? d_means + (b0 + r) * 3 : scratch_xyz;
        FeatureRowBackward(L, params, nm, means + (b0 + r) * 3, sc.dF.data() + (r - b) * D, &ws.taps[r],
                           &ws.samples[r * C], block, dxyz);
      }
    });
    const auto t1 = Clock::now();
    // One plane per task: no two threads write the same plane, and each plane sums its rows in
    // row order.
    pool.ParallelFor(NP, 1, [&](int64_t pb, int64_t pe, int) {
      for (int64_t pi = pb; pi < pe; ++pi) {
        T* grad = d_params + L.planes[pi].offset;
        for (size_t r = 0; r < bn; ++r) {
          if (r + kPrefetchRows < bn) {
            const PlaneTaps<T>& ahead = ws.taps[pi * block + r + kPrefetchRows];
            for (size_t o = 0; o < 2 * C * sizeof(T); o += 64) {
              __builtin_prefetch(reinterpret_cast<const char*>(grad + ahead.off00) + o, 1);
              __builtin_prefetch(reinterpret_cast<const char*>(grad + ahead.off00 + ahead.row) + o, 1);
            }
          }
          internal::ScatterPlane(grad, ws.taps[pi * block + r], C, &ws.samples[(pi * block + r) * C]);
        }
      }
    });
    rows_ms += std::chrono::duration<double, std::milli>(t1 - t0).count();
    scatter_ms += std::chrono::duration<double, std::milli>(Clock::now() - t1).count();
  }
  ws_outer.last_rows_ms = rows_ms;
  ws_outer.last_scatter_ms = scatter_ms;
  for (int t = 0; t < nt; ++t) {
    const T* g = ws.threads[t].mlp_grad.data();
    T* out = d_params + L.grid_size;
    for (size_t i = 0; i < mlp_size; ++i) out[i] += g[i];
  }
}

template void FieldForward<float>(const FieldLayout&, const float*, const FieldQuery&, const float*, const uint32_t*,
                                  size_t, float*, float*, ThreadPool&, FieldWorkspace&);
template void FieldForward<double>(const FieldLayout&, const double*, const FieldQuery&, const double*,
                                   const uint32_t*, size_t, double*, double*, ThreadPool&, FieldWorkspace&);
template void SpatialFeatures<float>(const FieldLayout&, const float*, const FieldQuery&, const float*,
                                     const uint32_t*, size_t, float*, ThreadPool&);
template void SpatialFeatures<double>(const FieldLayout&, const double*, const FieldQuery&, const double*,
                                      const uint32_t*, size_t, double*, ThreadPool&);
template void FieldForwardCached<float>(const FieldLayout&, const float*, const FieldQuery&, const float*,
                                        const uint32_t*, const float*, size_t, float*, float*, ThreadPool&,
                                        FieldWorkspace&);
template void FieldForwardCached<double>(const FieldLayout&, const double*, const FieldQuery&, const double*,
                                         const uint32_t*, const double*, size_t, double*, double*, ThreadPool&,
                                         FieldWorkspace&);
template void FieldBackward<float>(const FieldLayout&, const float*, const FieldQuery&, const float*, size_t,
                                   const float*, const float*, float*, float*, ThreadPool&, FieldWorkspace&);
template void FieldBackward<double>(const FieldLayout&, const double*, const FieldQuery&, const double*, size_t,
                                    const double*, const double*, double*, double*, ThreadPool&, FieldWorkspace&);

}  // namespace streetsim::field
