// The extended deformation field (extended_config.h for the composition): S3Gaussian's HexPlane,
// trunk and heads (a DeformationField, unchanged) plus the seed paper's modules in their own flat
// parameter array. Forward and backward over a batch of Gaussians on the cpu, float (training,
// serving) and double (gradient checks), multithreaded in chunks like field_eval.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/deformation_field.h"
#include "scene/field/extended/extended_config.h"

namespace streetsim::field {

class ExtendedField {
 public:
  // `base` keeps its parameters (a fresh spec init or a prior clip's field); the extension starts
  // from InitExtendedParams.
  static absl::StatusOr<ExtendedField> Create(DeformationField base, const ExtendedFieldConfig& config, uint64_t seed);
  static absl::StatusOr<ExtendedField> FromParams(DeformationField base, const ExtendedFieldConfig& config,
                                                  std::vector<float> params);

  const DeformationField& base() const { return base_; }
  DeformationField& mutable_base() { return base_; }
  const ExtendedFieldConfig& config() const { return config_; }
  const ExtendedLayout& layout() const { return layout_; }
  const std::vector<float>& params() const { return params_; }
  std::vector<float>& mutable_params() { return params_; }

 private:
  ExtendedField(DeformationField base, const ExtendedFieldConfig& config, ExtendedLayout layout,
                std::vector<float> params)
      : base_(std::move(base)), config_(config), layout_(std::move(layout)), params_(std::move(params)) {}
  DeformationField base_;
  ExtendedFieldConfig config_;
  ExtendedLayout layout_;
  std::vector<float> params_;
};

// Everything a pass reads, in the pass's scalar type (the double gradient checks hold their own
// parameter copies).
template <typename T>
struct ExtModel {
  const FieldLayout* base_layout = nullptr;
  const T* base_params = nullptr;  // [base_layout->total]
  const ExtendedFieldConfig* config = nullptr;
  const ExtendedLayout* layout = nullptr;
  const T* ext_params = nullptr;   // [layout->total()]
  FieldAabb aabb;
};
ExtModel<float> ModelOf(const ExtendedField& f);

struct ExtPass {
  double time_coord = 0;    // DeformationField::TimeCoordinate
  bool training = false;    // VAE: z = μ + σ ⊙ ε (training) or z = μ
  uint64_t noise_seed = 0;  // ε of Gaussian g, latent i: a pure function of (seed, g, i), so the
                            // backward recomputes the forward's ε on any thread
};

// Canonical Gaussians (trainer layout). opacity_logits, log_scales, rotations: only read with the
// encoder on (may be null otherwise).
template <typename T>
struct ExtInputs {
  size_t n = 0;
  const T* means = nullptr;           // [n*3]
  const T* opacity_logits = nullptr;  // [n]
  const T* log_scales = nullptr;      // [n*3]
  const T* rotations = nullptr;       // [n*4] (w, x, y, z)
};

// Outputs [n * k] (null: not wanted). dscale / drot / dopacity: only with the decoder.
template <typename T>
struct ExtOutputs {
  T* dx = nullptr;        // 3
  T* dsh = nullptr;       // 48, ΔSH[k][c] at 3k + c
  T* dscale = nullptr;    // 3, added to log-scales
  T* drot = nullptr;      // 4, added to the raw quaternion
  T* dopacity = nullptr;  // 1, added to the opacity logit
};

// dL/d(outputs) (null = zero).
template <typename T>
struct ExtOutputGrads {
  const T* d_dx = nullptr;
  const T* d_dsh = nullptr;
  const T* d_dscale = nullptr;
  const T* d_drot = nullptr;
  const T* d_dopacity = nullptr;
};

// Gradients ADDED to (null: not wanted, except d_base and d_ext).
template <typename T>
struct ExtInputGrads {
  T* d_base = nullptr;            // [base_layout->total]: planes and S3Gaussian's MLP
  T* d_ext = nullptr;             // [layout->total()]
  T* d_means = nullptr;           // [n*3]
  T* d_opacity_logits = nullptr;  // [n]    (encoder only)
  T* d_log_scales = nullptr;      // [n*3]  (encoder only)
  T* d_rotations = nullptr;       // [n*4]  (encoder only)
};

class ExtWorkspace {
 public:
  ExtWorkspace();
  ~ExtWorkspace();
  struct Impl;
  Impl& impl() { return *impl_; }

 private:
  std::unique_ptr<Impl> impl_;
};

// Returns Σ over Gaussians of KL(N(μ, σ²) || N(0, I)) (0 without the VAE).
template <typename T>
absl::StatusOr<double> ExtendedForward(const ExtModel<T>& model, const ExtPass& pass, const ExtInputs<T>& in,
                                       const ExtOutputs<T>& out, ThreadPool& pool, ExtWorkspace& ws);

// Backward of ExtendedForward (same pass, same inputs) with the KL term `kl_weight` · Σ KL added to
// the loss (the caller picks kl_weight = β / n for a mean, with its warm-up). Returns Σ KL.
template <typename T>
absl::StatusOr<double> ExtendedBackward(const ExtModel<T>& model, const ExtPass& pass, const ExtInputs<T>& in,
                                        const ExtOutputGrads<T>& d_out, double kl_weight, const ExtInputGrads<T>& grads,
                                        ThreadPool& pool, ExtWorkspace& ws);

}  // namespace streetsim::field
