#include "scene/field/extended/extended_serving.h"

#include <algorithm>
#include <limits>

#include "absl/strings/str_cat.h"
#include "scene/field/spatial_order.h"

namespace streetsim::field {

namespace {
constexpr size_t kAnalysisChunk = 32768;  // Gaussians whose statistics are kept at once
// Channels of the analysis, side by side: Δx, ΔSH, then the decoder's Δs.
constexpr int kSh0 = 3, kScale0 = kSh0 + kShOutputs, kRot0 = kScale0 + kDecoderScaleOutputs,
              kOp0 = kRot0 + kDecoderRotationOutputs, kDecoderWidth = kOp0 + kDecoderOpacityOutputs;
}  // namespace

void ExtCompactInputs::Gather(const GaussianStore& g, const uint32_t* rows, size_t n, size_t offset) {
  means.resize(n * 3);
  opacity_logits.resize(n);
  log_scales.resize(n * 3);
  rotations.resize(n * 4);
  for (size_t r = 0; r < n; ++r) {
    const size_t i = offset + rows[r];
    std::copy_n(&g.means[i * 3], 3, &means[r * 3]);
    opacity_logits[r] = g.opacity_logits[i];
    std::copy_n(&g.log_scales[i * 3], 3, &log_scales[r * 3]);
    std::copy_n(&g.rotations[i * 4], 4, &rotations[r * 4]);
  }
}

absl::StatusOr<std::unique_ptr<ExtServingField>> ExtServingField::Create(ExtendedField field, GaussianStore canonical,
                                                                         const StaticSkipOptions& o,
                                                                         ThreadPool& pool, const Device* device) {
  if (absl::Status s = canonical.Validate(); !s.ok()) return s;
  if (canonical.sh_degree != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
  }
  if (canonical.size() > std::numeric_limits<uint32_t>::max()) {
    return absl::InvalidArgumentError("ExtServingField: more than 2^32 Gaussians");
  }
  if (o.enabled && (o.num_samples < 2 || o.num_samples > 100000)) {
    return absl::InvalidArgumentError(absl::StrCat("static skip: ", o.num_samples, " samples, want 2..100000"));
  }
  std::unique_ptr<ExtServingField> sf(new ExtServingField(std::move(field)));
  if (device) sf->SetDevice(device->name, device->forward);
  sf->canonical_ = std::move(canonical);
  sf->baked_ = sf->canonical_;
  const size_t n = sf->canonical_.size();
  if (o.enabled) {
    if (absl::Status s = sf->Analyse(o, pool); !s.ok()) return s;
  } else {
    sf->rows_.resize(n);
    for (size_t i = 0; i < n; ++i) sf->rows_[i] = static_cast<uint32_t>(i);
  }
  const GaussianStore& c = sf->canonical_;
  // Evaluation order along a Morton curve: neighbouring rows share texels (cache), see spatial_order.h.
  if (o.spatial_order) {
    sf->rows_ = SpatialOrder(sf->field_.base().aabb(), c.means.data(), sf->rows_.size(), sf->rows_.data(), pool);
  }
  sf->inputs_.Gather(c, sf->rows_.data(), sf->rows_.size());
  sf->current_ = sf->baked_;
  return sf;
}

absl::Status ExtServingField::Analyse(const StaticSkipOptions& o, ThreadPool& pool) {
  const GaussianStore& g = canonical_;
  const size_t n = g.size();
  const bool dec = field_.config().decoder;
  const int S = o.num_samples;
  // Samples in an order that finds motion early: both ends, the middle, then the rest.
  std::vector<int> order = {0, S - 1};
  if (S > 2) order.push_back(S / 2);
  for (int s = 1; s < S - 1; ++s) {
    if (s != S / 2) order.push_back(s);
  }
  auto still_static = [&](const DeltaRanges& r, size_t i) {
    if (!MotionAndColourStatic(r, i, kShOutputs, o)) return false;
    return !dec || (r.max_range(i, kScale0, kDecoderScaleOutputs) < o.log_scale_threshold &&
                    r.max_range(i, kRot0, kDecoderRotationOutputs) < o.rotation_threshold &&
                    r.max_range(i, kOp0, kDecoderOpacityOutputs) < o.opacity_threshold);
  };
  std::vector<uint32_t> cand;  // rows of the chunk that are static so far
  ExtCompactInputs in;
  std::vector<float> dx, dsh, dscale, drot, dop;
  DeltaRanges ranges;
  for (size_t c0 = 0; c0 < n; c0 += kAnalysisChunk) {
    const size_t cn = std::min(kAnalysisChunk, n - c0);
    ranges.Reset(cn, dec ? kDecoderWidth : kScale0);
    cand.resize(cn);
    for (size_t i = 0; i < cn; ++i) cand[i] = static_cast<uint32_t>(i);
    for (int s : order) {
      // A Gaussian seen moving stays dynamic: later samples evaluate the candidates only (a
      // field that moves everything costs 2 evaluations here, not S).
      const size_t m = cand.size();
      if (m == 0) break;
      in.Gather(g, cand.data(), m, c0);
      dx.resize(m * 3), dsh.resize(m * kShOutputs);
      dscale.resize(dec ? m * kDecoderScaleOutputs : 0), drot.resize(dec ? m * kDecoderRotationOutputs : 0);
      dop.resize(dec ? m * kDecoderOpacityOutputs : 0);
      ExtPass pass;  // inference: z = μ
      pass.time_coord = field_.base().NormalisedTime(static_cast<double>(s) / (S - 1));
      const ExtOutputs<float> out{dx.data(), dsh.data(), dec ? dscale.data() : nullptr, dec ? drot.data() : nullptr,
                                  dec ? dop.data() : nullptr};
      absl::StatusOr<double> kl = Evaluate(pass, in.view(), out, pool);
      if (!kl.ok()) return kl.status();
      if (dec) {
        ranges.Add({{dx.data(), 3, 3},
                    {dsh.data(), kShOutputs, kShOutputs},
                    {dscale.data(), kDecoderScaleOutputs, kDecoderScaleOutputs},
                    {drot.data(), kDecoderRotationOutputs, kDecoderRotationOutputs},
                    {dop.data(), kDecoderOpacityOutputs, kDecoderOpacityOutputs}},
                   cand.data(), m, pool);
      } else {
        ranges.Add({{dx.data(), 3, 3}, {dsh.data(), kShOutputs, kShOutputs}}, cand.data(), m, pool);
      }
      cand.erase(std::remove_if(cand.begin(), cand.end(), [&](uint32_t i) { return !still_static(ranges, i); }),
                 cand.end());
    }
    // What is left was static at every sample: its time-mean Δs are baked in.
    std::vector<uint8_t> is_static(cn, 0);
    for (uint32_t i : cand) is_static[i] = 1;
    for (size_t i = 0; i < cn; ++i) {
      const size_t row = c0 + i;
      if (!is_static[i]) {
        rows_.push_back(static_cast<uint32_t>(row));
        continue;
      }
      for (int k = 0; k < 3; ++k) baked_.means[row * 3 + k] += ranges.mean(i, k);
      for (int k = 0; k < kShOutputs; ++k) baked_.sh[row * kShOutputs + k] += ranges.mean(i, kSh0 + k);
      if (!dec) continue;
      for (int k = 0; k < 3; ++k) baked_.log_scales[row * 3 + k] += ranges.mean(i, kScale0 + k);
      for (int k = 0; k < 4; ++k) baked_.rotations[row * 4 + k] += ranges.mean(i, kRot0 + k);
      baked_.opacity_logits[row] += ranges.mean(i, kOp0);
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<double> ExtServingField::Evaluate(const ExtPass& pass, const ExtInputs<float>& in,
                                                 const ExtOutputs<float>& out, ThreadPool& pool) {
  absl::StatusOr<double> kl = absl::UnknownError("not evaluated");
  if (device_forward_) {
    kl = device_forward_(field_, pass, in, out);
    if (!kl.ok()) {
      DeviceFailed(kl.status());
      device_forward_ = nullptr;
    }
  }
  if (!kl.ok()) kl = ExtendedForward<float>(ModelOf(field_), pass, in, out, pool, *ws_);
  // The decoder's Δlog-scale as the trainer applied it (DeformSceneExt): bounded.
  if (kl.ok() && out.dscale != nullptr) {
    const float bound = field_.config().decoder_max_dlog_scale;
    pool.ParallelFor(static_cast<int64_t>(in.n), 8192, [&](int64_t b, int64_t e, int) {
      BoundDecoderLogScales(bound, out.dscale + b * kDecoderScaleOutputs,
                            static_cast<size_t>(e - b) * kDecoderScaleOutputs);
    });
  }
  return kl;
}

void ExtServingField::SetDevice(std::string device, ExtDeviceForward forward) {
  device_ = std::move(device);
  device_forward_ = std::move(forward);
}

absl::StatusOr<const GaussianStore*> ExtServingField::At(int64_t time_us, ThreadPool& pool) {
  const double coord = field_.base().TimeCoordinate(time_us);
  if (have_current_ && coord == last_coord_) return &current_;
  const size_t nd = rows_.size();
  const bool dec = field_.config().decoder;
  dx_.resize(nd * 3);
  dsh_.resize(nd * kShOutputs);
  dscale_.resize(dec ? nd * 3 : 0);
  drot_.resize(dec ? nd * 4 : 0);
  dopacity_.resize(dec ? nd : 0);
  if (nd > 0) {
    ExtPass pass;  // inference: z = μ
    pass.time_coord = coord;
    const ExtOutputs<float> out{dx_.data(), dsh_.data(), dec ? dscale_.data() : nullptr,
                                dec ? drot_.data() : nullptr, dec ? dopacity_.data() : nullptr};
    absl::StatusOr<double> kl = Evaluate(pass, inputs_.view(), out, pool);
    if (!kl.ok()) return kl.status();
  }
  ++evaluations_;
  const GaussianStore& c = canonical_;
  pool.ParallelFor(static_cast<int64_t>(nd), 8192, [&](int64_t b, int64_t e, int) {
    for (int64_t r = b; r < e; ++r) {
      const size_t i = rows_[r];
      for (int k = 0; k < 3; ++k) current_.means[i * 3 + k] = c.means[i * 3 + k] + dx_[r * 3 + k];
      for (int k = 0; k < kShOutputs; ++k) {
        current_.sh[i * kShOutputs + k] = c.sh[i * kShOutputs + k] + dsh_[r * kShOutputs + k];
      }
      if (!dec) continue;
      for (int k = 0; k < 3; ++k) current_.log_scales[i * 3 + k] = c.log_scales[i * 3 + k] + dscale_[r * 3 + k];
      for (int k = 0; k < 4; ++k) current_.rotations[i * 4 + k] = c.rotations[i * 4 + k] + drot_[r * 4 + k];
      current_.opacity_logits[i] = c.opacity_logits[i] + dopacity_[r];
    }
  });
  last_coord_ = coord;
  have_current_ = true;
  return &current_;
}

}  // namespace streetsim::field
