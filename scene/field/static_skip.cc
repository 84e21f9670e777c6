#include "scene/field/static_skip.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/field/spatial_order.h"

namespace streetsim::field {

namespace {
constexpr size_t kAnalysisChunk = 32768;  // Gaussians whose statistics are kept at once
}  // namespace

void DeltaRanges::Reset(size_t rows, int width) {
  rows_ = rows;
  width_ = width;
  samples_ = 0;
  lo_.assign(rows * width, std::numeric_limits<float>::max());
  hi_.assign(rows * width, std::numeric_limits<float>::lowest());
  sum_.assign(rows * width, 0.0);
}

void DeltaRanges::Add(std::initializer_list<Block> blocks, ThreadPool& pool) { Add(blocks, nullptr, rows_, pool); }

void DeltaRanges::Add(std::initializer_list<Block> blocks, const uint32_t* rows, size_t n, ThreadPool& pool) {
  const std::vector<Block> bs(blocks);
  ++samples_;
  pool.ParallelFor(static_cast<int64_t>(n), 4096, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b; i < e; ++i) {
      size_t j = (rows ? rows[i] : i) * width_;
      for (const Block& blk : bs) {
        for (int k = 0; k < blk.count; ++k, ++j) {
          const float v = blk.data[i * blk.stride + k];
          lo_[j] = std::min(lo_[j], v);
          hi_[j] = std::max(hi_[j], v);
          sum_[j] += v;
        }
      }
    }
  });
}

double DeltaRanges::max_range(size_t row, int k0, int count) const {
  double m = 0;
  for (int k = k0; k < k0 + count; ++k) m = std::max(m, double(range(row, k)));
  return m;
}

bool MotionAndColourStatic(const DeltaRanges& r, size_t row, int sh_values, const StaticSkipOptions& o) {
  double box2 = 0;
  for (int k = 0; k < 3; ++k) box2 += double(r.range(row, k)) * r.range(row, k);
  return std::sqrt(box2) < o.motion_threshold_m && r.max_range(row, 3, sh_values) < o.sh_threshold;
}

void ServedScene::DeviceFailed(const absl::Status& why) {
  LOG(WARNING) << "field evaluation on " << device_ << " failed, evaluating on the cpu from now on: " << why;
  device_ = "cpu";
}

absl::StatusOr<StaticAnalysis> AnalyseStatic(const DeformationField& field, const GaussianStore& g,
                                             const StaticSkipOptions& o, ThreadPool& pool,
                                             const FieldDeviceForward* device) {
  if (absl::Status s = g.Validate(); !s.ok()) return s;
  if (o.num_samples < 2 || o.num_samples > 100000) {
    return absl::InvalidArgumentError(absl::StrCat("static skip: ", o.num_samples, " samples, want 2..100000"));
  }
  const size_t n = g.size();
  const int K3 = g.sh_coeffs() * 3;
  StaticAnalysis out;
  out.mean_dx.assign(n * 3, 0.0f);
  out.mean_dsh.assign(n * K3, 0.0f);
  FieldWorkspace ws;
  std::vector<float> dx, dsh, spatial;
  DeltaRanges ranges;
  const int S = o.num_samples;
  for (size_t c0 = 0; c0 < n; c0 += kAnalysisChunk) {
    const size_t cn = std::min(kAnalysisChunk, n - c0);
    dx.resize(cn * 3);
    dsh.resize(cn * kShOutputs);
    ranges.Reset(cn, 3 + K3);  // Δx then ΔSH
    // The spatial planes do not depend on time: sampled once per chunk, not once per sample.
    if (!device) {
      spatial.resize(cn * field.layout().feature_dim());
      SpatialFeatures<float>(field.layout(), field.params().data(), field.QueryAtCoordinate(0),
                             g.means.data() + c0 * 3, nullptr, cn, spatial.data(), pool);
    }
    for (int s = 0; s < S; ++s) {
      const double coord = field.NormalisedTime(static_cast<double>(s) / (S - 1));
      if (device) {
        if (absl::Status st = (*device)(field, field.QueryAtCoordinate(coord),
                                        std::span<const float>(g.means.data() + c0 * 3, cn * 3), &dx, &dsh);
            !st.ok()) {
          return st;
        }
        if (dx.size() != cn * 3 || dsh.size() != cn * kShOutputs) {
          return absl::InternalError("static skip: the device returned the wrong number of outputs");
        }
      } else {
        FieldForwardCached<float>(field.layout(), field.params().data(), field.QueryAtCoordinate(coord),
                                  g.means.data() + c0 * 3, nullptr, spatial.data(), cn, dx.data(), dsh.data(),
                                  pool, ws);
      }
      ranges.Add({{dx.data(), 3, 3}, {dsh.data(), kShOutputs, K3}}, pool);
    }
    for (size_t i = 0; i < cn; ++i) {
      for (int k = 0; k < 3; ++k) out.mean_dx[(c0 + i) * 3 + k] = ranges.mean(i, k);
      for (int k = 0; k < K3; ++k) out.mean_dsh[(c0 + i) * K3 + k] = ranges.mean(i, 3 + k);
      if (!MotionAndColourStatic(ranges, i, K3, o) || !o.enabled) {
        out.dynamic_rows.push_back(static_cast<uint32_t>(c0 + i));
      }
    }
  }
  return out;
}

absl::StatusOr<ServingField> ServingField::Create(DeformationField field, GaussianStore canonical,
                                                  const StaticSkipOptions& options, ThreadPool& pool,
                                                  const Device* device) {
  if (canonical.size() > std::numeric_limits<uint32_t>::max()) {
    return absl::InvalidArgumentError("ServingField: more than 2^32 Gaussians");
  }
  ServingField sf;
  const size_t n = canonical.size();
  const int K3 = canonical.sh_coeffs() * 3;
  sf.baked_ = canonical;
  bool device_ok = device != nullptr;
  if (options.enabled) {
    absl::StatusOr<StaticAnalysis> a =
        AnalyseStatic(field, canonical, options, pool, device ? &device->forward : nullptr);
    if (!a.ok() && device) {
      sf.device_ = device->name;
      sf.DeviceFailed(a.status());
      device_ok = false;
      a = AnalyseStatic(field, canonical, options, pool);
    }
    if (!a.ok()) return a.status();
    sf.dynamic_rows_ = std::move(a->dynamic_rows);
    std::vector<uint8_t> dynamic(n, 0);
    for (uint32_t r : sf.dynamic_rows_) dynamic[r] = 1;
    for (size_t i = 0; i < n; ++i) {
      if (dynamic[i]) continue;
      for (int k = 0; k < 3; ++k) sf.baked_.means[i * 3 + k] += a->mean_dx[i * 3 + k];
      for (int k = 0; k < K3; ++k) sf.baked_.sh[i * K3 + k] += a->mean_dsh[i * K3 + k];
    }
  } else {
    if (absl::Status s = canonical.Validate(); !s.ok()) return s;
    sf.dynamic_rows_.resize(n);
    for (size_t i = 0; i < n; ++i) sf.dynamic_rows_[i] = static_cast<uint32_t>(i);
  }
  // Evaluation order along a Morton curve: neighbouring rows share texels (cache), see spatial_order.h.
  if (options.spatial_order) sf.dynamic_rows_ = SpatialOrder(field.aabb(), canonical.means.data(), sf.dynamic_rows_.size(),
                                  sf.dynamic_rows_.data(), pool);
  sf.cache_spatial_ = options.cache_spatial_features;
  if (options.cache_spatial_features && !device_ok) {  // on a device: built only if it fails later
    sf.spatial_.resize(sf.dynamic_rows_.size() * field.layout().feature_dim());
    SpatialFeatures<float>(field.layout(), field.params().data(), field.QueryAtCoordinate(0), canonical.means.data(),
                           sf.dynamic_rows_.data(), sf.dynamic_rows_.size(), sf.spatial_.data(), pool);
  }
  sf.field_ = std::move(field);
  sf.canonical_ = std::move(canonical);
  sf.current_ = sf.baked_;
  if (device_ok) sf.SetDevice(device->name, device->forward);
  return sf;
}

void ServingField::SetDevice(std::string device, FieldDeviceForward forward) {
  device_ = std::move(device);
  device_forward_ = std::move(forward);
  device_means_.resize(dynamic_rows_.size() * 3);
  for (size_t r = 0; r < dynamic_rows_.size(); ++r) {
    std::copy_n(&canonical_.means[dynamic_rows_[r] * 3], 3, &device_means_[r * 3]);
  }
  std::vector<float>().swap(spatial_);  // 512 B per dynamic Gaussian the device does not need
}

void ServingField::ForwardOnCpu(double coord, ThreadPool& pool) {
  const size_t nd = dynamic_rows_.size();
  float* dsh = canonical_.sh_coeffs() > 0 ? dsh_.data() : nullptr;
  if (cache_spatial_ && spatial_.empty() && nd > 0) {  // freed for a device that has since failed
    spatial_.resize(nd * field_.layout().feature_dim());
    SpatialFeatures<float>(field_.layout(), field_.params().data(), field_.QueryAtCoordinate(0),
                           canonical_.means.data(), dynamic_rows_.data(), nd, spatial_.data(), pool);
  }
  if (spatial_.empty()) {
    FieldForward<float>(field_.layout(), field_.params().data(), field_.QueryAtCoordinate(coord),
                        canonical_.means.data(), dynamic_rows_.data(), nd, dx_.data(), dsh, pool, *ws_);
  } else {
    FieldForwardCached<float>(field_.layout(), field_.params().data(), field_.QueryAtCoordinate(coord),
                              canonical_.means.data(), dynamic_rows_.data(), spatial_.data(), nd, dx_.data(), dsh,
                              pool, *ws_);
  }
}

absl::StatusOr<const GaussianStore*> ServingField::At(int64_t time_us, ThreadPool& pool) {
  const double coord = field_.TimeCoordinate(time_us);
  if (have_current_ && coord == last_coord_) return &current_;
  const size_t nd = dynamic_rows_.size();
  const int K3 = canonical_.sh_coeffs() * 3;
  dx_.resize(nd * 3);
  dsh_.resize(nd * kShOutputs);
  bool done = false;
  if (device_forward_ && nd > 0) {
    absl::Status s = device_forward_(field_, field_.QueryAtCoordinate(coord), device_means_, &dx_,
                                     K3 > 0 ? &dsh_ : nullptr);
    // The device may resize what it fills; anything else than the cpu's sizes is a failure too.
    if (s.ok() && (dx_.size() != nd * 3 || (K3 > 0 && dsh_.size() != nd * kShOutputs))) {
      s = absl::InternalError("the device returned outputs of the wrong size");
    }
    done = s.ok();
    if (!done) {
      DeviceFailed(s);
      device_forward_ = nullptr;
      std::vector<float>().swap(device_means_);
      dx_.resize(nd * 3);
      dsh_.resize(nd * kShOutputs);
    }
  }
  if (!done) ForwardOnCpu(coord, pool);
  ++evaluations_;
  pool.ParallelFor(static_cast<int64_t>(nd), 8192, [&](int64_t b, int64_t e, int) {
    for (int64_t r = b; r < e; ++r) {
      const size_t i = dynamic_rows_[r];
      for (int k = 0; k < 3; ++k) current_.means[i * 3 + k] = canonical_.means[i * 3 + k] + dx_[r * 3 + k];
      for (int k = 0; k < K3; ++k) current_.sh[i * K3 + k] = canonical_.sh[i * K3 + k] + dsh_[r * kShOutputs + k];
    }
  });
  last_coord_ = coord;
  have_current_ = true;
  return &current_;
}

}  // namespace streetsim::field
