#include "scene/field/serving_form.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>
#include <mutex>
#include <type_traits>
#include <utility>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"

namespace streetsim::field {

namespace {

constexpr int kRestShValues = (kShCoeffs - 1) * 3;  // SH bands 1-3

// Where channel `c` of group `g` lives in a store: array, stride per Gaussian, offset.
template <typename F>
struct TargetOf {
  F* data;
  int stride, offset;
};
using Source = TargetOf<const float>;

// The modelled channels of `groups` in table order (a const store gives read-only Sources).
template <typename Store, typename F = std::conditional_t<std::is_const_v<Store>, const float, float>>
std::vector<TargetOf<F>> Targets(uint32_t groups, Store* s) {
  std::vector<TargetOf<F>> t;
  for (int g = 0; g < kFormGroups; ++g) {
    if (!(groups & (1u << g))) continue;
    const GroupSpan<F> span = SpanOf(static_cast<FormGroup>(g), s);
    for (int c = 0; c < kFormGroupChannels[g]; ++c) t.push_back({span.data, span.stride, span.offset + c});
  }
  return t;
}

constexpr uint32_t kAllGroups = (1u << kFormGroups) - 1;

// The group of each channel Targets(groups, ...) lists, in the same order.
std::vector<int> GroupOfChannels(uint32_t groups) {
  std::vector<int> out;
  for (int g = 0; g < kFormGroups; ++g) {
    if (groups & (1u << g)) out.insert(out.end(), kFormGroupChannels[g], g);
  }
  return out;
}

float ValueAt(const Source& s, size_t i) { return s.data[i * s.stride + s.offset]; }

}  // namespace

absl::Status ServingFormOptions::Validate() const {
  if (degree != 1 && degree != 3) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: degree ", degree, ", want 1 or 3"));
  }
  if (segments_per_cell < 1 || max_segments_per_cell < segments_per_cell || max_segments_per_cell > 64) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: ", segments_per_cell, " to ", max_segments_per_cell,
                                                   " segments per cell, want 1 <= first <= max <= 64"));
  }
  if (samples_per_segment < 2 || samples_per_segment > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("serving form: ", samples_per_segment, " samples per segment, want 2..64"));
  }
  if (appearance_rank < 1 || appearance_rank > kMaxAppearanceRank) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: appearance rank ", appearance_rank, ", want 1..",
                                                   kMaxAppearanceRank));
  }
  if (!(max_position_error_m > 0)) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: max_position_error_m ", max_position_error_m,
                                                   " must be > 0"));
  }
  return absl::OkStatus();
}

int ServingForm::modelled_channels() const {
  int n = 0;
  for (int g = 1; g < kFormGroups; ++g) n += (groups_ & (1u << g)) ? kFormGroupChannels[g] : 0;
  return n;
}

double ServingForm::SplineAxis::Tau(int64_t time_us) const {
  if (time_range.end_us <= time_range.start_us) return 0;
  const double tau = (static_cast<double>(time_us) - static_cast<double>(time_range.start_us)) /
                     (static_cast<double>(time_range.end_us) - static_cast<double>(time_range.start_us));
  return std::clamp(tau, 0.0, 1.0);
}

ServingForm::Spline ServingForm::SplineAxis::AtTau(double tau) const {
  Spline sp;
  const int segments = control_points - degree;
  const double u = tau * segments;
  const int k = std::clamp(static_cast<int>(std::floor(u)), 0, segments - 1);
  const double s = u - k, s2 = s * s, s3 = s2 * s;
  sp.k = k;
  sp.taps = degree + 1;
  if (degree == 1) {
    sp.w[0] = static_cast<float>(1 - s);
    sp.w[1] = static_cast<float>(s);
  } else {
    // Uniform cubic B-spline.
    sp.w[0] = static_cast<float>((1 - s) * (1 - s) * (1 - s) / 6);
    sp.w[1] = static_cast<float>((3 * s3 - 6 * s2 + 4) / 6);
    sp.w[2] = static_cast<float>((-3 * s3 + 3 * s2 + 3 * s + 1) / 6);
    sp.w[3] = static_cast<float>(s3 / 6);
  }
  for (int j = 0; j < sp.taps; ++j) sp.line += sp.w[j] * static_cast<float>(k + j);
  sp.line /= static_cast<float>(control_points - 1);
  return sp;
}

void ServingForm::EvaluateInto(double tau, GaussianStore* out, ThreadPool& pool, uint32_t groups) const {
  const Spline sp = spline_axis().AtTau(tau);
  if (degree_ == 1) {
    tables_.Evaluate<2>(sp.k, sp.w, sp.line, rows_.data(), out, pool, groups);
  } else {
    tables_.Evaluate<4>(sp.k, sp.w, sp.line, rows_.data(), out, pool, groups);
  }
}

absl::StatusOr<const GaussianStore*> ServingForm::At(int64_t time_us, ThreadPool& pool) {
  const double tau = Tau(time_us);
  if (tau == last_tau_) return &current_;
  if (tau == geometry_tau_) {
    EvaluateInto(tau, &current_, pool, kAppearanceGroups);  // the same evaluation, completed
  } else {
    EvaluateInto(tau, &current_, pool);
    ++evaluations_;
  }
  last_tau_ = geometry_tau_ = tau;
  return &current_;
}

absl::StatusOr<const GaussianStore*> ServingForm::GeometryAt(int64_t time_us, ThreadPool& pool) {
  const double tau = Tau(time_us);
  if (tau == last_tau_ || tau == geometry_tau_) return &current_;
  EvaluateInto(tau, &current_, pool, ~kAppearanceGroups);
  geometry_tau_ = tau;
  last_tau_ = -1;  // the appearance is another time's
  ++evaluations_;
  return &current_;
}

absl::Status ServingForm::WritePlanesAt(int64_t time_us, const ScenePlanes& planes, ThreadPool& pool) {
  if (planes.n != current_.size() || planes.sh_degree != current_.sh_degree) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: planes of ", planes.n, " Gaussians of SH degree ",
                                                   planes.sh_degree, " for a form of ", current_.size(),
                                                   " of degree ", current_.sh_degree));
  }
  const double tau = Tau(time_us);
  const Spline sp = spline_axis().AtTau(tau);
  // The store's geometry too, unless it already holds this time's.
  GaussianStore* geometry = tau == last_tau_ || tau == geometry_tau_ ? nullptr : &current_;
  const bool ok = degree_ == 1
                      ? tables_.EvaluateIntoPlanes<2>(sp.k, sp.w, sp.line, rows_.data(), planes, pool, geometry)
                      : tables_.EvaluateIntoPlanes<4>(sp.k, sp.w, sp.line, rows_.data(), planes, pool, geometry);
  if (!ok) {
    last_tau_ = geometry_tau_ = -1;  // the store may be part-written: the next At evaluates it whole
    return absl::InternalError("serving form: a value came out non-finite or a rotation zero");
  }
  if (geometry) {
    geometry_tau_ = tau;
    last_tau_ = -1;
    ++evaluations_;
  }
  return absl::OkStatus();
}

ParamsChange ServingForm::changes() const {
  ParamsChange c;
  c.rows = rows_.data();
  c.num_rows = rows_.size();
  c.means = true;
  c.sh_coeffs = models(FormGroup::kShBands) ? kShCoeffs : models(FormGroup::kColour) ? 1 : 0;
  c.log_scales = models(FormGroup::kLogScale);
  c.rotations = models(FormGroup::kRotation);
  c.opacity = models(FormGroup::kOpacity);
  return c;
}

absl::Status ServingForm::Check(ServedScene& exact, const std::vector<int64_t>& fit_us, ThreadPool& pool) {
  const size_t nd = rows_.size();
  const int S = static_cast<int>(fit_us.size());
  // The form against the exact field halfway between the fit samples.
  GaussianStore probe = current_;
  const std::vector<int> group_of = GroupOfChannels(kAllGroups);
  position_error_m_.assign(nd, 0.0f);
  std::mutex mu;
  for (int s = 0; s + 1 < S; ++s) {
    const int64_t t = (fit_us[s] + fit_us[s + 1]) / 2;
    absl::StatusOr<const GaussianStore*> g = exact.At(t, pool);
    if (!g.ok()) return g.status();
    const GaussianStore& y = **g;
    EvaluateInto(Tau(t), &probe, pool);
    // Every group, modelled or not (one that is not must not change: a probe may have missed it).
    const std::vector<Source> got = Targets(kAllGroups, &std::as_const(probe)), want = Targets(kAllGroups, &y);
    pool.ParallelFor(static_cast<int64_t>(nd), 4096, [&](int64_t b, int64_t e, int) {
      std::array<float, kFormGroups> local{};
      for (int64_t r = b; r < e; ++r) {
        const size_t i = rows_[r];
        double d2 = 0;
        for (int c = 0; c < 3; ++c) d2 += std::pow(double(ValueAt(got[c], i)) - ValueAt(want[c], i), 2);
        position_error_m_[r] = std::max(position_error_m_[r], static_cast<float>(std::sqrt(d2)));
        local[0] = std::max(local[0], position_error_m_[r]);
        for (size_t c = 3; c < got.size(); ++c) {
          local[group_of[c]] = std::max(local[group_of[c]], std::abs(ValueAt(got[c], i) - ValueAt(want[c], i)));
        }
      }
      std::lock_guard<std::mutex> lock(mu);
      for (int grp = 0; grp < kFormGroups; ++grp) error_.max[grp] = std::max(error_.max[grp], local[grp]);
    });
  }
  error_.check_samples = S - 1;
  std::vector<float> sorted = position_error_m_;
  const size_t p99 = std::min(sorted.size() - 1, static_cast<size_t>(0.99 * static_cast<double>(sorted.size())));
  std::nth_element(sorted.begin(), sorted.begin() + p99, sorted.end());
  error_.position_p99_m = sorted[p99];
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<ServingForm>> ServingForm::Build(ServedScene& exact, const ServingFormOptions& o,
                                                                ThreadPool& pool) {
  if (absl::Status s = o.Validate(); !s.ok()) return s;
  const int cells = std::max(1, exact.time_cells());
  double previous_p99 = 0;
  for (int per_cell = o.segments_per_cell;; per_cell = std::min(2 * per_cell, o.max_segments_per_cell)) {
    absl::StatusOr<std::unique_ptr<ServingForm>> f =
        Fit(exact, o.degree, cells * per_cell, o.samples_per_segment, pool, o.appearance_rank);
    if (!f.ok()) return f;
    const double p99 = (*f)->error_.position_p99_m;
    if (p99 <= o.max_position_error_m || per_cell >= o.max_segments_per_cell) return f;
    // Give up early when the last doubling's gain, kept up to the most segments, cannot reach the
    // bound (a field with motion finer than the spline: the caller serves the exact field).
    if (previous_p99 > 0) {
      const double gain = std::max(1.0, previous_p99 / std::max(p99, 1e-12));
      const double doublings_left = std::log2(double(o.max_segments_per_cell) / per_cell);
      if (p99 / std::pow(gain, doublings_left) > o.max_position_error_m) return f;
    }
    previous_p99 = p99;
    LOG(INFO) << "serving form: " << cells * per_cell << " segments leave a p99 position error of " << p99 * 1000
              << " mm, fitting again with more";
  }
}

absl::StatusOr<std::unique_ptr<ServingForm>> ServingForm::Fit(ServedScene& exact, int degree, int segments,
                                                              int samples_per_segment, ThreadPool& pool,
                                                              int appearance_rank) {
  if ((degree != 1 && degree != 3) || segments < 1 || segments > 1024 || samples_per_segment < 2 ||
      samples_per_segment > 64 || appearance_rank < 1 || appearance_rank > kMaxAppearanceRank) {
    return absl::InvalidArgumentError(absl::StrCat("serving form: degree ", degree, ", ", segments, " segments, ",
                                                   samples_per_segment, " samples per segment, appearance rank ",
                                                   appearance_rank));
  }
  std::unique_ptr<ServingForm> f(new ServingForm());
  f->time_range_ = exact.time_range();
  f->degree_ = degree;
  f->control_points_ = segments + degree;
  const FieldTimeRange tr = f->time_range_;
  auto time_at = [&](double tau) {
    return tr.start_us + static_cast<int64_t>(std::llround(tau * static_cast<double>(tr.end_us - tr.start_us)));
  };
  auto sample = [&](int64_t t) -> absl::StatusOr<const GaussianStore*> {
    absl::StatusOr<const GaussianStore*> g = exact.At(t, pool);
    if (g.ok() && (*g)->sh_degree != 3) return absl::FailedPreconditionError("serving form: SH degree 3 expected");
    return g;
  };
  absl::StatusOr<const GaussianStore*> first = sample(tr.start_us);
  if (!first.ok()) return first.status();
  f->current_ = **first;
  f->groups_ = 1u << static_cast<int>(FormGroup::kPosition);  // position always: a form's tables start with it
  std::vector<uint32_t> rows = exact.dynamic_rows();
  std::sort(rows.begin(), rows.end());
  if (tr.end_us <= tr.start_us || rows.empty()) return f;  // one time, or nothing moves

  // Which other groups move: probes over the range (the error check below covers every group).
  for (double tau : {1.0 / 3, 2.0 / 3, 1.0}) {
    absl::StatusOr<const GaussianStore*> g = sample(time_at(tau));
    if (!g.ok()) return g.status();
    for (int grp = 1; grp < kFormGroups; ++grp) {
      if (f->models(static_cast<FormGroup>(grp))) continue;
      const std::vector<Source> a = Targets(1u << grp, &std::as_const(f->current_)), b = Targets(1u << grp, *g);
      const bool moves = std::any_of(rows.begin(), rows.end(), [&](uint32_t i) {
        for (size_t c = 0; c < a.size(); ++c) {
          if (ValueAt(a[c], i) != ValueAt(b[c], i)) return true;
        }
        return false;
      });
      if (moves) f->groups_ |= 1u << grp;
    }
  }
  const int M = f->control_points_, Co = f->modelled_channels(), C = 3 + Co;
  const size_t nd = rows.size();

  // Least squares per Gaussian and channel: (B^T B) x = B^T y. B^T y is accumulated one sample at a
  // time (each sample touches degree + 1 control points); B^T B is banded and the same for every
  // Gaussian, so its Cholesky factor is computed once and each right-hand side solved in the band.
  const int S = segments * samples_per_segment + 1;
  const int bw = degree;
  std::vector<int64_t> fit_us(S);
  std::vector<int> fit_k(S);
  std::vector<std::array<float, 4>> fit_w(S);
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(M, M);
  for (int s = 0; s < S; ++s) {
    fit_us[s] = time_at(static_cast<double>(s) / (S - 1));
    const Spline sp = f->spline_axis().At(fit_us[s]);
    fit_k[s] = sp.k;
    std::copy_n(sp.w, 4, fit_w[s].data());
    for (int a = 0; a <= degree; ++a)
      for (int b = 0; b <= degree; ++b) A(fit_k[s] + a, fit_k[s] + b) += double(fit_w[s][a]) * fit_w[s][b];
  }
  Eigen::MatrixXd L = Eigen::MatrixXd::Zero(M, M);  // banded Cholesky factor of A
  for (int i = 0; i < M; ++i) {
    for (int j = std::max(0, i - bw); j <= i; ++j) {
      double sum = A(i, j);
      for (int k = std::max(0, i - bw); k < j; ++k) sum -= L(i, k) * L(j, k);
      if (i == j) {
        if (!(sum > 0)) return absl::InternalError("serving form: the fit's normal matrix is singular");
        L(i, i) = std::sqrt(sum);
      } else {
        L(i, j) = sum / L(j, j);
      }
    }
  }
  std::vector<float> coef(nd * M * C, 0.0f);
  // SH bands the form does not model keep their time-mean.
  const bool bands = f->models(FormGroup::kShBands);
  std::vector<float> rest_mean(bands ? 0 : nd * kRestShValues, 0.0f);
  for (int s = 0; s < S; ++s) {
    absl::StatusOr<const GaussianStore*> g = sample(fit_us[s]);
    if (!g.ok()) return g.status();
    const GaussianStore& y = **g;
    const std::vector<Source> src = Targets(f->groups_, &y);
    const int k = fit_k[s];
    const std::array<float, 4> w = fit_w[s];
    pool.ParallelFor(static_cast<int64_t>(nd), 2048, [&](int64_t b, int64_t e, int) {
      for (int64_t r = b; r < e; ++r) {
        const size_t i = rows[r];
        float* a = &coef[(r * M + k) * C];
        for (int c = 0; c < C; ++c) {
          const float v = src[c].data[i * src[c].stride + src[c].offset];
          for (int j = 0; j <= degree; ++j) a[j * C + c] += w[j] * v;
        }
        if (!bands) {
          const float* rest = &y.sh[i * kShOutputs + 3];
          for (int q = 0; q < kRestShValues; ++q) rest_mean[r * kRestShValues + q] += rest[q] / S;
        }
      }
    });
  }
  std::vector<float> Lf(static_cast<size_t>(M) * M);
  for (int i = 0; i < M; ++i)
    for (int j = 0; j < M; ++j) Lf[i * M + j] = static_cast<float>(L(i, j));
  pool.ParallelFor(static_cast<int64_t>(nd), 1024, [&](int64_t b, int64_t e, int) {
    for (int64_t r = b; r < e; ++r) {
      float* x = &coef[r * M * C];
      for (int i = 0; i < M; ++i) {  // L z = B^T y
        for (int q = std::max(0, i - bw); q < i; ++q)
          for (int c = 0; c < C; ++c) x[i * C + c] -= Lf[i * M + q] * x[q * C + c];
        for (int c = 0; c < C; ++c) x[i * C + c] /= Lf[i * M + i];
      }
      for (int i = M - 1; i >= 0; --i) {  // L^T x = z
        for (int q = i + 1; q <= std::min(M - 1, i + bw); ++q)
          for (int c = 0; c < C; ++c) x[i * C + c] -= Lf[q * M + i] * x[q * C + c];
        for (int c = 0; c < C; ++c) x[i * C + c] /= Lf[i * M + i];
      }
    }
  });

  f->tables_ = FormTables::Quantise(coef, nd, M, f->groups_, appearance_rank, pool);
  std::vector<float>().swap(coef);
  if (!bands) {
    for (size_t r = 0; r < nd; ++r) {
      std::copy_n(&rest_mean[r * kRestShValues], kRestShValues, &f->current_.sh[rows[r] * kShOutputs + 3]);
    }
  }
  f->rows_ = std::move(rows);
  std::vector<float>().swap(rest_mean);

  if (absl::Status st = f->Check(exact, fit_us, pool); !st.ok()) return st;
  f->last_tau_ = -1;  // current_ holds the start's time-invariant values; the first At evaluates
  return f;
}

}  // namespace streetsim::field
