#include "scene/field/serving_form_tables.h"

#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <cstddef>
#include <cstring>
#if defined(__AVX2__)
#include <immintrin.h>
#endif

#include "render/common/plane_tiles.h"

namespace streetsim::field {

namespace {

constexpr int kPowerIterations = 30;

template <typename F, typename Store>
GroupSpan<F> SpanIn(FormGroup g, Store* s) {
  const int K3 = s->sh_coeffs() * 3;
  switch (g) {
    case FormGroup::kPosition: return {s->means.data(), 3, 0};
    case FormGroup::kColour: return {s->sh.data(), K3, 0};
    case FormGroup::kLogScale: return {s->log_scales.data(), 3, 0};
    case FormGroup::kRotation: return {s->rotations.data(), 4, 0};
    case FormGroup::kOpacity: return {s->opacity_logits.data(), 1, 0};
    case FormGroup::kShBands: return {s->sh.data(), K3, 3};
  }
  return {nullptr, 0, 0};
}

// Symmetric int8 quantisation of n values with a bfloat16 step: returns the step.
float QuantiseSymmetric(const float* x, int n, int stride, int8_t* q, int q_stride) {
  float m = 0;
  for (int i = 0; i < n; ++i) m = std::max(m, std::abs(x[i * stride]));
  const float step = m > 0 ? FromBf16(Bf16AtLeast(m / 127.0f)) : 0.0f;
  for (int i = 0; i < n; ++i) {
    q[i * q_stride] = static_cast<int8_t>(step > 0 ? std::clamp(std::round(x[i * stride] / step), -127.0f, 127.0f) : 0.0f);
  }
  return step;
}

// S3Gaussian's appearance at rank 1 into one Gaussian's 48 SH floats (restrict: the store and
// the tables never overlap, which lets the fixed-count loops vectorise without alias checks).
inline void AppearanceRank1(float* __restrict dst, const int8_t* __restrict qb, const int8_t* __restrict qv,
                            float off0, float st0, float off1, float st1, float a) {
  for (int c = 0; c < 3; ++c) dst[c] = off0 + st0 * static_cast<float>(qb[c]) + a * static_cast<float>(qv[c]);
  for (int c = 3; c < 48; ++c) dst[c] = off1 + st1 * static_cast<float>(qb[c]) + a * static_cast<float>(qv[c]);
}

}  // namespace

GroupSpan<float> SpanOf(FormGroup g, GaussianStore* s) { return SpanIn<float>(g, s); }
GroupSpan<const float> SpanOf(FormGroup g, const GaussianStore* s) { return SpanIn<const float>(g, s); }

uint16_t ToBf16(float x) {
  uint32_t b = std::bit_cast<uint32_t>(x);
  b += 0x7fff + ((b >> 16) & 1);  // round to nearest even
  return static_cast<uint16_t>(b >> 16);
}

uint16_t Bf16AtLeast(float x) {
  uint16_t b = static_cast<uint16_t>(std::bit_cast<uint32_t>(x) >> 16);  // truncation: <= x for x >= 0
  if (FromBf16(b) < x) ++b;
  return b;
}

float FromBf16(uint16_t b) { return std::bit_cast<float>(static_cast<uint32_t>(b) << 16); }

int FormTables::Block::group_count() const { return std::popcount(groups); }

void FormTables::Block::Resize(size_t rows, int control_points) {
  base_offset.assign(rows * group_count(), 0.0f);
  base_step.assign(rows * group_count(), 0);
  q_base.assign(rows * channels, 0);
  scale.assign(rows * rank, 0);
  q_u.assign(rows * rank * control_points, 0);
  q_v.assign(rows * rank * channels, 0);
}

std::vector<FormTables::Block> FormTables::BlocksOf(uint32_t groups, int appearance_rank, int control_points) {
  std::vector<Block> blocks;
  if (groups & kAppearanceGroups) {
    Block b;
    b.groups = groups & kAppearanceGroups;
    for (int g = 0; g < kFormGroups; ++g) b.channels += (b.groups & (1u << g)) ? kFormGroupChannels[g] : 0;
    b.rank = std::clamp(appearance_rank, 1, std::min(b.channels, control_points));
    blocks.push_back(b);
  }
  for (FormGroup g : {FormGroup::kLogScale, FormGroup::kRotation, FormGroup::kOpacity}) {
    const uint32_t bit = 1u << static_cast<int>(g);
    if (!(groups & bit)) continue;
    Block b;
    b.groups = bit;
    b.channels = kFormGroupChannels[static_cast<int>(g)];
    b.rank = std::min(b.channels, control_points);
    blocks.push_back(b);
  }
  return blocks;
}

int FormTables::appearance_rank() const {
  return !blocks_.empty() && (blocks_[0].groups & kAppearanceGroups) ? blocks_[0].rank : 0;
}

size_t FormTables::bytes() const {
  size_t n = position_ends_.size() * sizeof(float) + position_step_.size() * sizeof(uint16_t) + q_position_.size();
  for (const Block& b : blocks_) {
    n += b.base_offset.size() * sizeof(float) + (b.base_step.size() + b.scale.size()) * sizeof(uint16_t) +
         b.q_base.size() + b.q_u.size() + b.q_v.size();
  }
  return n;
}

FormTables FormTables::Quantise(const std::vector<float>& coef, size_t rows, int control_points, uint32_t groups,
                                int appearance_rank, ThreadPool& pool) {
  FormTables t;
  t.rows_ = rows;
  t.control_points_ = control_points;
  t.groups_ = groups;
  const int M = control_points;
  t.position_ends_.assign(rows * 6, 0.0f);
  t.position_step_.assign(rows * 3, 0);
  t.q_position_.assign(rows * M * 3, 0);
  t.blocks_ = BlocksOf(groups, appearance_rank, M);
  for (Block& b : t.blocks_) b.Resize(rows, M);
  // Each block's columns in coef: its groups' channels, in group order like coef's.
  int C = 3;
  std::vector<int> start(kFormGroups, 0);
  for (int g = 1; g < kFormGroups; ++g) {
    if (!(groups & (1u << g))) continue;
    start[g] = C;
    C += kFormGroupChannels[g];
  }
  std::vector<std::vector<int>> cols(t.blocks_.size());
  for (size_t bi = 0; bi < t.blocks_.size(); ++bi) {
    for (int g = 1; g < kFormGroups; ++g) {
      if (!(t.blocks_[bi].groups & (1u << g))) continue;
      for (int c = 0; c < kFormGroupChannels[g]; ++c) cols[bi].push_back(start[g] + c);
    }
  }
  pool.ParallelFor(static_cast<int64_t>(rows), 512, [&](int64_t b, int64_t e, int) {
    std::vector<float> z, u, v, residual(M);
    for (int64_t r = b; r < e; ++r) {
      const float* x = &coef[static_cast<size_t>(r) * M * C];
      // Position: the line between the ends and the residual from it.
      for (int c = 0; c < 3; ++c) {
        const float p0 = x[c], p1 = x[(M - 1) * C + c];
        t.position_ends_[r * 6 + c] = p0;
        t.position_ends_[r * 6 + 3 + c] = p1;
        for (int m = 0; m < M; ++m) residual[m] = x[m * C + c] - (p0 + (p1 - p0) * static_cast<float>(m) / (M - 1));
        const float step = QuantiseSymmetric(residual.data(), M, 1, &t.q_position_[r * M * 3 + c], 3);
        t.position_step_[r * 3 + c] = ToBf16(step);  // exact: step is a bfloat16 already
      }
      for (size_t bi = 0; bi < t.blocks_.size(); ++bi) {
        Block& bl = t.blocks_[bi];
        const int n = bl.channels;
        // Z: the block's control points less their time-mean [M][n].
        z.assign(static_cast<size_t>(M) * n, 0.0f);
        std::vector<float> mean(n, 0.0f);
        for (int m = 0; m < M; ++m)
          for (int c = 0; c < n; ++c) mean[c] += x[m * C + cols[bi][c]] / M;
        for (int m = 0; m < M; ++m)
          for (int c = 0; c < n; ++c) z[m * n + c] = x[m * C + cols[bi][c]] - mean[c];
        // The time-mean: int8 per channel, an offset and step per group.
        int c0 = 0, gi = 0;
        for (int g = 1; g < kFormGroups; ++g) {
          if (!(bl.groups & (1u << g))) continue;
          const int ng = kFormGroupChannels[g];
          const auto [lo, hi] = std::minmax_element(&mean[c0], &mean[c0] + ng);
          const float off = 0.5f * (*lo + *hi);
          const float step = *hi > *lo ? FromBf16(Bf16AtLeast(0.5f * (*hi - *lo) / 127.0f)) : 0.0f;
          bl.base_offset[r * bl.group_count() + gi] = off;
          bl.base_step[r * bl.group_count() + gi] = ToBf16(step);
          for (int c = c0; c < c0 + ng; ++c) {
            bl.q_base[r * n + c] = static_cast<int8_t>(
                step > 0 ? std::clamp(std::round((mean[c] - off) / step), -127.0f, 127.0f) : 0.0f);
          }
          c0 += ng;
          ++gi;
        }
        // The change over time, one rank-1 term at a time by power iteration on Z (deflated):
        // u = Z v, v = Z^T u. Started from the control point that changes most.
        for (int j = 0; j < bl.rank; ++j) {
          u.assign(M, 0.0f);
          v.assign(n, 0.0f);
          int best = 0;
          float best_norm = -1;
          for (int m = 0; m < M; ++m) {
            float s = 0;
            for (int c = 0; c < n; ++c) s += z[m * n + c] * z[m * n + c];
            if (s > best_norm) best_norm = s, best = m;
          }
          if (!(best_norm > 0)) break;  // nothing left to model: the term stays zero
          for (int c = 0; c < n; ++c) v[c] = z[best * n + c];
          for (int it = 0; it < kPowerIterations; ++it) {
            double norm = 0;
            for (float a : v) norm += double(a) * a;
            const float inv = static_cast<float>(1.0 / std::sqrt(std::max(norm, 1e-300)));
            for (float& a : v) a *= inv;
            for (int m = 0; m < M; ++m) {
              float s = 0;
              for (int c = 0; c < n; ++c) s += z[m * n + c] * v[c];
              u[m] = s;
            }
            if (it + 1 == kPowerIterations) break;  // v unit, u = Z v: u v^T is the term
            std::fill(v.begin(), v.end(), 0.0f);
            for (int m = 0; m < M; ++m)
              for (int c = 0; c < n; ++c) v[c] += z[m * n + c] * u[m];
          }
          for (int m = 0; m < M; ++m)
            for (int c = 0; c < n; ++c) z[m * n + c] -= u[m] * v[c];
          const float su = QuantiseSymmetric(u.data(), M, 1, &bl.q_u[(r * bl.rank + j) * M], 1);
          const float sv = QuantiseSymmetric(v.data(), n, 1, &bl.q_v[(r * bl.rank + j) * n], 1);
          bl.scale[r * bl.rank + j] = ToBf16(su * sv);
        }
      }
    }
  });
  return t;
}

template <int kTaps>
void FormTables::PositionAt(size_t r, int k, const float* w, float line, float p[3]) const {
  const float* ends = &position_ends_[r * 6];
  const int8_t* qp = &q_position_[(r * control_points_ + k) * 3];
  for (int c = 0; c < 3; ++c) {
    float s = 0;
    for (int j = 0; j < kTaps; ++j) s += w[j] * qp[3 * j + c];
    p[c] = ends[c] + (ends[3 + c] - ends[c]) * line + FromBf16(position_step_[r * 3 + c]) * s;
  }
}

template <int kTaps>
void FormTables::AppearanceRank1At(size_t r, int k, const float* w, float* __restrict sh48) const {
  const Block& bl = blocks_[0];
  const int8_t* qu = &bl.q_u[r * control_points_ + k];
  float s = 0;
  for (int t = 0; t < kTaps; ++t) s += w[t] * qu[t];
  const float a = FromBf16(bl.scale[r]) * s;
  AppearanceRank1(sh48, &bl.q_base[r * 48], &bl.q_v[r * 48], bl.base_offset[r * 2], FromBf16(bl.base_step[r * 2]),
                  bl.base_offset[r * 2 + 1], FromBf16(bl.base_step[r * 2 + 1]), a);
}

template <int kTaps>
void FormTables::BlockAt(const Block& bl, size_t r, int k, const float* w, float* vals) const {
  const int M = control_points_;
  const int n = bl.channels, R = bl.rank, G = bl.group_count();
  float ut[kMaxAppearanceRank + 4];
  for (int j = 0; j < R; ++j) {
    const int8_t* qu = &bl.q_u[(r * R + j) * M + k];
    float s = 0;
    for (int t = 0; t < kTaps; ++t) s += w[t] * qu[t];
    ut[j] = FromBf16(bl.scale[r * R + j]) * s;
  }
  // One pass per group for the time-mean and one per term, in `vals` (nothing aliases it, so the
  // loops vectorise).
  const int8_t* qb = &bl.q_base[r * n];
  const int8_t* qv = &bl.q_v[r * R * n];
  int c0 = 0, gi = 0;
  for (int g = 1; g < kFormGroups; ++g) {
    if (!(bl.groups & (1u << g))) continue;
    const int count = kFormGroupChannels[g];
    const float off = bl.base_offset[r * G + gi], step = FromBf16(bl.base_step[r * G + gi]);
    for (int c = c0; c < c0 + count; ++c) vals[c] = off + step * static_cast<float>(qb[c]);
    c0 += count;
    ++gi;
  }
  for (int j = 0; j < R; ++j) {
    const float a = ut[j];
    const int8_t* q = qv + j * n;
    for (int c = 0; c < n; ++c) vals[c] += a * static_cast<float>(q[c]);
  }
}

bool FormTables::IsS3Rank1(int sh_degree) const {
  return blocks_.size() == 1 && blocks_[0].groups == kAppearanceGroups && blocks_[0].rank == 1 && sh_degree == 3;
}

template <int kTaps>
void FormTables::Evaluate(int k, const float* w, float line, const uint32_t* rows, GaussianStore* out,
                          ThreadPool& pool, uint32_t groups) const {
  const bool position = groups & (1u << static_cast<int>(FormGroup::kPosition));
  struct Run {
    GroupSpan<float> span;
    int count;
  };
  std::vector<const Block*> blocks;
  std::vector<std::vector<Run>> runs;
  for (const Block& bl : blocks_) {
    if (!(bl.groups & groups)) continue;
    blocks.push_back(&bl);
    runs.emplace_back();
    for (int g = 1; g < kFormGroups; ++g) {
      if (bl.groups & (1u << g)) runs.back().push_back({SpanOf(static_cast<FormGroup>(g), out), kFormGroupChannels[g]});
    }
  }
  // S3Gaussian's form at the default rank: the DC and the bands are one run of 48 floats in the
  // store, written with fixed trip counts (the general path takes ~2x as long).
  const bool s3_rank1 = !blocks.empty() && IsS3Rank1(out->sh_degree);
  pool.ParallelFor(static_cast<int64_t>(rows_), 4096, [&](int64_t b, int64_t e, int) {
    float vals[64];  // a block's channels (48 at most)
    for (int64_t r = b; r < e; ++r) {
      const size_t i = rows[r];
      if (position) PositionAt<kTaps>(r, k, w, line, &out->means[i * 3]);
      if (s3_rank1) {
        AppearanceRank1At<kTaps>(r, k, w, out->sh.data() + i * 48);
        continue;
      }
      for (size_t bi = 0; bi < blocks.size(); ++bi) {
        BlockAt<kTaps>(*blocks[bi], r, k, w, vals);
        int c0 = 0;
        for (const Run& run : runs[bi]) {
          std::copy_n(vals + c0, run.count, run.span.data + i * run.span.stride + run.span.offset);
          c0 += run.count;
        }
      }
    }
  });
}

namespace {

float* PlaneOf(FormGroup g, int c, const ScenePlanes& p) {
  switch (g) {
    case FormGroup::kPosition: return p.mean[c];
    case FormGroup::kColour: return p.sh + static_cast<size_t>(c) * p.sh_plane;
    case FormGroup::kLogScale: return p.log_scale[c];
    case FormGroup::kRotation: return p.rotation[c];
    case FormGroup::kOpacity: return p.opacity_logit;
    case FormGroup::kShBands: return p.sh + static_cast<size_t>(3 + c) * p.sh_plane;
  }
  return nullptr;
}

}  // namespace

template <int kTaps>
bool FormTables::EvaluateIntoPlanes(int k, const float* w, float line, const uint32_t* rows, const ScenePlanes& out,
                                    ThreadPool& pool, GaussianStore* geometry) const {
  using planes::NonFinite;
  // Per block: the plane of each channel and, for a geometric block with `geometry`, the store's
  // place of each channel (element i * stride + offset).
  struct StoreChannel {
    float* data;
    int stride, offset;
  };
  std::vector<std::vector<float*>> block_planes(blocks_.size());
  std::vector<std::vector<StoreChannel>> block_store(blocks_.size());
  for (size_t bi = 0; bi < blocks_.size(); ++bi) {
    for (int g = 1; g < kFormGroups; ++g) {
      if (!(blocks_[bi].groups & (1u << g))) continue;
      for (int c = 0; c < kFormGroupChannels[g]; ++c) {
        block_planes[bi].push_back(PlaneOf(static_cast<FormGroup>(g), c, out));
        if (geometry && !(blocks_[bi].groups & kAppearanceGroups)) {
          const GroupSpan<float> span = SpanOf(static_cast<FormGroup>(g), geometry);
          block_store[bi].push_back({span.data, span.stride, span.offset + c});
        }
      }
    }
  }
  float* means = geometry ? geometry->means.data() : nullptr;
  const bool s3_rank1 = IsS3Rank1(out.sh_degree);
  const bool rotation = groups_ & (1u << static_cast<int>(FormGroup::kRotation));
  const size_t plane = out.sh_plane;
  const bool lines = plane % 16 == 0 && reinterpret_cast<uintptr_t>(out.sh) % 64 == 0;
  std::atomic<bool> bad{false};
  pool.ParallelFor(static_cast<int64_t>(rows_), 4096, [&](int64_t b, int64_t e, int) {
    uint32_t nf = 0;
    bool streamed = false;
    alignas(64) float tile[16 * 48];  // [row][value]
    float vals[64];
    for (int64_t r = b; r < e;) {
      const size_t i = rows[r];
      float p[3];
#if defined(__AVX2__)
      // Sixteen consecutive rows from a cache-line start: one whole line of each SH plane, computed
      // row by row into `tile` and streamed out through registers (one pass over the planes).
      if (s3_rank1 && lines && i % 16 == 0 && r + 16 <= e && rows[r + 15] == i + 15) {
        for (int j = 0; j < 16; ++j) {
          PositionAt<kTaps>(r + j, k, w, line, p);
          for (int c = 0; c < 3; ++c) out.mean[c][i + j] = p[c], nf |= NonFinite(p[c]);
          if (means) std::copy_n(p, 3, means + (i + j) * 3);
          AppearanceRank1At<kTaps>(r + j, k, w, tile + j * 48);
        }
        nf |= planes::StreamRows16(tile, 48, 48, out.sh + i, plane);
        streamed = true;
        r += 16;
        continue;
      }
#endif
      PositionAt<kTaps>(r, k, w, line, p);
      for (int c = 0; c < 3; ++c) out.mean[c][i] = p[c], nf |= NonFinite(p[c]);
      if (means) std::copy_n(p, 3, means + i * 3);
      if (s3_rank1) {
        AppearanceRank1At<kTaps>(r, k, w, vals);
        for (int c = 0; c < 48; ++c) out.sh[c * plane + i] = vals[c], nf |= NonFinite(vals[c]);
      } else {
        for (size_t bi = 0; bi < blocks_.size(); ++bi) {
          BlockAt<kTaps>(blocks_[bi], r, k, w, vals);
          const std::vector<float*>& dst = block_planes[bi];
          for (size_t c = 0; c < dst.size(); ++c) dst[c][i] = vals[c], nf |= NonFinite(vals[c]);
          const std::vector<StoreChannel>& st = block_store[bi];
          for (size_t c = 0; c < st.size(); ++c) st[c].data[i * st[c].stride + st[c].offset] = vals[c];
        }
        if (rotation) {
          float q2 = 0;
          for (int c = 0; c < 4; ++c) q2 += out.rotation[c][i] * out.rotation[c][i];
          nf |= q2 < 1e-20f;
        }
      }
      ++r;
    }
#if defined(__AVX2__)
    if (streamed) _mm_sfence();  // streaming stores are weakly ordered: publish them before the join
#endif
    if (nf) bad.store(true, std::memory_order_relaxed);
  });
  return !bad.load();
}

FormTables::RecordLayout FormTables::MakeRecordLayout() const {
  RecordLayout l;
  const uint32_t M = static_cast<uint32_t>(control_points_);
  auto words_of_bytes = [](uint32_t bytes) { return (bytes + 3) / 4; };
  uint32_t w = 1;  // the row index
  l.ends = w, w += 6;
  l.position_step = w, w += words_of_bytes(3 * 2);
  l.q_position = w, w += words_of_bytes(M * 3);
  for (const Block& b : blocks_) {
    RecordLayout::Block d;
    d.groups = b.groups;
    d.channels = static_cast<uint32_t>(b.channels);
    d.rank = static_cast<uint32_t>(b.rank);
    d.group_count = static_cast<uint32_t>(b.group_count());
    d.base_offset = w, w += d.group_count;
    d.base_step = w, w += words_of_bytes(d.group_count * 2);
    d.scale = w, w += words_of_bytes(d.rank * 2);
    d.q_base = w, w += words_of_bytes(d.channels);
    d.q_u = w, w += words_of_bytes(d.rank * M);
    d.q_v = w, w += words_of_bytes(d.rank * d.channels);
    l.blocks.push_back(d);
  }
  l.record_words = w;
  return l;
}

static_assert(std::endian::native == std::endian::little, "FormTables::PackRecords copies bytes");

void FormTables::PackRecords(const RecordLayout& l, const uint32_t* rows, size_t begin, size_t end,
                             uint32_t* out) const {
  const size_t M = static_cast<size_t>(control_points_);
  std::fill(out, out + (end - begin) * l.record_words, 0u);
  for (size_t r = begin; r < end; ++r) {
    uint32_t* rec = out + (r - begin) * l.record_words;
    // On a little-endian host a byte copy packs the low element first, as the kernel reads.
    auto put = [rec](uint32_t word, const void* src, size_t bytes) {
      std::memcpy(reinterpret_cast<std::byte*>(rec + word), src, bytes);
    };
    rec[0] = rows[r];
    put(l.ends, &position_ends_[r * 6], 6 * sizeof(float));
    put(l.position_step, &position_step_[r * 3], 3 * sizeof(uint16_t));
    put(l.q_position, &q_position_[r * M * 3], M * 3);
    for (size_t bi = 0; bi < blocks_.size(); ++bi) {
      const Block& b = blocks_[bi];
      const RecordLayout::Block& d = l.blocks[bi];
      const size_t G = d.group_count, R = d.rank, n = d.channels;
      put(d.base_offset, &b.base_offset[r * G], G * sizeof(float));
      put(d.base_step, &b.base_step[r * G], G * sizeof(uint16_t));
      put(d.scale, &b.scale[r * R], R * sizeof(uint16_t));
      put(d.q_base, &b.q_base[r * n], n);
      put(d.q_u, &b.q_u[r * R * M], R * M);
      put(d.q_v, &b.q_v[r * R * n], R * n);
    }
  }
}

template void FormTables::Evaluate<2>(int, const float*, float, const uint32_t*, GaussianStore*, ThreadPool&,
                                      uint32_t) const;
template void FormTables::Evaluate<4>(int, const float*, float, const uint32_t*, GaussianStore*, ThreadPool&,
                                      uint32_t) const;
template bool FormTables::EvaluateIntoPlanes<2>(int, const float*, float, const uint32_t*, const ScenePlanes&,
                                                ThreadPool&, GaussianStore*) const;
template bool FormTables::EvaluateIntoPlanes<4>(int, const float*, float, const uint32_t*, const ScenePlanes&,
                                                ThreadPool&, GaussianStore*) const;

}  // namespace streetsim::field
