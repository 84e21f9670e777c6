#include "scene/field/deformation_field.h"

#include <algorithm>
#include <cmath>
#include <random>

#include "absl/strings/str_cat.h"
#include "scene/field/huge_pages.h"

namespace streetsim::field {

absl::Status ValidateAabb(const FieldAabb& aabb) {
  for (int k = 0; k < 3; ++k) {
    if (!std::isfinite(aabb.min[k]) || !std::isfinite(aabb.max[k]) || !(aabb.max[k] > aabb.min[k])) {
      return absl::InvalidArgumentError(absl::StrCat("field: AABB axis ", k, " [", aabb.min[k], ", ", aabb.max[k],
                                                     "] is empty or not finite"));
    }
  }
  return absl::OkStatus();
}

namespace {
absl::Status ValidateTimeRange(const FieldTimeRange& r) {
  if (r.end_us < r.start_us) {
    return absl::InvalidArgumentError(absl::StrCat("field: time range end ", r.end_us, " us < start ", r.start_us, " us"));
  }
  return absl::OkStatus();
}
}  // namespace

template <typename T>
void InitFieldParams(const FieldConfig& config, const FieldLayout& L, uint64_t seed, std::vector<T>* params) {
  params->assign(L.total, T(0));
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> plane_init(config.plane_init_lo, config.plane_init_hi);
  for (const PlaneInfo& p : L.planes) {
    T* d = params->data() + p.offset;
    const size_t sz = p.size(L.channels);
    if (PlaneHasTime(p.plane)) {
      std::fill(d, d + sz, T(1));
    } else {
      for (size_t i = 0; i < sz; ++i) d[i] = static_cast<T>(plane_init(rng));
    }
  }
  for (const DenseInfo* d : {&L.trunk, &L.pos1, &L.pos2, &L.sh1, &L.sh2}) {
    const double xavier = std::sqrt(6.0 / (d->in + d->out));
    const double bias = 1.0 / std::sqrt(static_cast<double>(d->in));
    std::uniform_real_distribution<double> uw(-xavier, xavier), ub(-bias, bias);
    for (size_t i = 0; i < static_cast<size_t>(d->out) * d->in; ++i) (*params)[d->w_offset + i] = static_cast<T>(uw(rng));
    for (int i = 0; i < d->out; ++i) (*params)[d->b_offset + i] = static_cast<T>(ub(rng));
  }
  if (config.zero_init_heads) {
    // After the draws, so that every other parameter keeps its spec value for the same seed.
    for (const DenseInfo* d : {&L.pos2, &L.sh2}) {
      std::fill_n(params->data() + d->w_offset, static_cast<size_t>(d->out) * d->in, T(0));
      std::fill_n(params->data() + d->b_offset, d->out, T(0));
    }
  }
}
template void InitFieldParams<float>(const FieldConfig&, const FieldLayout&, uint64_t, std::vector<float>*);
template void InitFieldParams<double>(const FieldConfig&, const FieldLayout&, uint64_t, std::vector<double>*);

absl::StatusOr<DeformationField> DeformationField::Create(const FieldConfig& config, const FieldAabb& aabb,
                                                          const FieldTimeRange& time_range, uint64_t seed) {
  if (absl::Status s = config.Validate(); !s.ok()) return s;
  if (absl::Status s = ValidateAabb(aabb); !s.ok()) return s;
  if (absl::Status s = ValidateTimeRange(time_range); !s.ok()) return s;
  DeformationField f;
  f.config_ = config;
  f.layout_ = FieldLayout::Make(config);
  f.aabb_ = aabb;
  f.time_range_ = time_range;
  InitFieldParams(config, f.layout_, seed, &f.params_);
  MoveToHugePages(&f.params_);
  return f;
}

absl::StatusOr<DeformationField> DeformationField::FromParams(const FieldConfig& config, const FieldAabb& aabb,
                                                              const FieldTimeRange& time_range,
                                                              std::vector<float> params) {
  if (absl::Status s = config.Validate(); !s.ok()) return s;
  if (absl::Status s = ValidateAabb(aabb); !s.ok()) return s;
  if (absl::Status s = ValidateTimeRange(time_range); !s.ok()) return s;
  DeformationField f;
  f.config_ = config;
  f.layout_ = FieldLayout::Make(config);
  if (params.size() != f.layout_.total) {
    return absl::InvalidArgumentError(
        absl::StrCat("field: ", params.size(), " parameters, the configuration needs ", f.layout_.total));
  }
  for (float v : params) {
    if (!std::isfinite(v)) return absl::InvalidArgumentError("field: non-finite parameter");
  }
  f.aabb_ = aabb;
  f.time_range_ = time_range;
  f.params_ = std::move(params);
  MoveToHugePages(&f.params_);
  return f;
}

double DeformationField::TimeCoordinate(int64_t time_us) const {
  const int64_t span = time_range_.end_us - time_range_.start_us;
  double tau = 0;
  // In double: time_us may be anything a client sends, the int64 difference could overflow.
  if (span > 0) {
    tau = std::clamp((static_cast<double>(time_us) - static_cast<double>(time_range_.start_us)) / span, 0.0, 1.0);
  }
  return NormalisedTime(tau);
}

FieldQuery DeformationField::QueryAtCoordinate(double time_coord) const {
  FieldQuery q;
  for (int k = 0; k < 3; ++k) {
    q.aabb_min[k] = aabb_.min[k];
    q.aabb_max[k] = aabb_.max[k];
  }
  q.time_coord = time_coord;
  return q;
}

}  // namespace streetsim::field
