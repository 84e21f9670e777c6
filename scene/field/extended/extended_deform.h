// Trainer and serving glue of the extended field (the counterpart of deformed_scene.h):
// canonical Gaussians + field + time -> deformed parameters; the rendered scene's GaussianGrads ->
// gradients of the planes and S3Gaussian's MLP (d_base, FieldAdamStep's layout), of the extension
// (d_ext, its own Adam group) and of the canonical Gaussians; the network group's Adam and
// schedule; the KL weight with its warm-up; a deformed GaussianStore for render / eval, and the
// way a loaded extended scene travels as a plain std::shared_ptr<const DeformationField>.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/field_adam.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::field {

// The extension's Adam group ("network"): method.md item 7's decoder learning rate 1.6e-3,
// log-linear to 1.6e-4 over lr_decay_steps fine iterations (the field groups' shape), not scaled
// by the scene extent (the rate is the paper's absolute one).
struct ExtHyper {
  double network_lr_init = 1.6e-3, network_lr_final = 1.6e-4;
  int lr_decay_steps = 30000;
  // `streetsim train --field-ext-lr-scale`: multiplies both ends of the rate. The base field's
  // rates have their own switches (FieldHyper::lr_scale / lr_decay_steps); a module grown on an
  // annealed field would otherwise learn at nearly the paper's full rate beside it.
  double lr_scale = 1.0;
};
double ExtNetworkLr(const ExtHyper& h, int64_t fine_iteration);
// β · min(1, fine_iteration / kl_warmup_iterations) (β alone without warm-up).
double ExtKlBeta(const ExtendedFieldConfig& c, int64_t fine_iteration);
// One Adam step (eps 1e-15, betas 0.9 / 0.999, PyTorch's formula) over the extension.
void ExtAdamStep(float* params, const float* grads, size_t n, ExtAdamState* state, double lr);

// The canonical parameters (SH degree 3, trainer layout).
struct ExtCanonicalView {
  size_t n = 0;
  const float* means = nullptr;           // [n*3]
  const float* sh = nullptr;              // [n*48]
  const float* log_scales = nullptr;      // [n*3]
  const float* rotations = nullptr;       // [n*4]
  const float* opacity_logits = nullptr;  // [n]
};

struct ExtDeformedScene {
  ExtPass pass;
  std::vector<float> dx, dsh, dscale, drot, dopacity;          // dscale as applied (bounded)
  std::vector<float> means, sh;                               // canonical + Δ
  std::vector<float> log_scales, rotations, opacity_logits;  // canonical + Δ (decoder only)
  double kl_sum = 0;
};

// Where DeformSceneExt / DeformBackwardExt evaluate the field: null members (the default) run
// ExtendedForward / ExtendedBackward<float> on the cpu with `field`'s parameters; the trainer's
// Vulkan path sets them to a VulkanExtendedField's Forward / Backward (same semantics).
struct ExtEvaluator {
  std::function<absl::StatusOr<double>(const ExtPass&, const ExtInputs<float>&, const ExtOutputs<float>&)> forward;
  std::function<absl::StatusOr<double>(const ExtPass&, const ExtInputs<float>&, const ExtOutputGrads<float>&, double,
                                       const ExtInputGrads<float>&)>
      backward;
};

absl::Status DeformSceneExt(const ExtendedField& field, const ExtPass& pass, const ExtCanonicalView& canonical,
                            ThreadPool& pool, ExtWorkspace& ws, ExtDeformedScene* out,
                            const ExtEvaluator& eval = {});
// `canonical` with the deformed arrays of `deformed` in place of the canonical ones.
GaussianParamsView ExtDeformedParamsView(const GaussianParamsView& canonical, const ExtDeformedScene& deformed);

struct ExtDeformLosses {
  double dx_l1 = 0, dsh_l1 = 0;  // means of |Δx|, |ΔSH|
  double kl_mean = 0;             // mean over Gaussians of KL
  double weighted = 0;            // lambda_dx dx_l1 + lambda_dsh dsh_l1 + kl_beta kl_mean
};

// DeformBackward for the extended field: adds dL/d(base) to d_base (resized on first use),
// dL/d(extension) to d_ext, and turns grads into dL/d(canonical): means (identity + sampling
// position + encoder), and with the encoder opacity / log-scales / rotations (identity + encoder
// inputs); the decoder's Δs take the rendered scene's gradients of what they were added to.
absl::StatusOr<ExtDeformLosses> DeformBackwardExt(const ExtendedField& field, const ExtCanonicalView& canonical,
                                                  const ExtDeformedScene& deformed, int active_degree,
                                                  const FieldHyper& hyper, double kl_beta, ThreadPool& pool,
                                                  ExtWorkspace& ws, GaussianGrads* grads, std::vector<float>* d_base,
                                                  std::vector<float>* d_ext, const ExtEvaluator& eval = {});

// `canonical` (SH degree 3) deformed at `time_us` (inference: z = μ).
absl::StatusOr<GaussianStore> ExtDeformedStore(const ExtendedField& field, const GaussianStore& canonical,
                                               int64_t time_us, ThreadPool& pool);

// A loaded extended scene as the std::shared_ptr<const DeformationField> that render / eval pass
// around (it points at the base field; the extension lives in the same allocation), and the
// lookup that finds the extension again from the base (nullptr for a plain field). The lookup is a
// process-wide table of live shared extended fields, entered here and left when the last owner
// goes.
std::shared_ptr<const DeformationField> ShareWithExtension(ExtendedField field);
std::shared_ptr<const ExtendedField> ExtensionOf(const DeformationField& base);

}  // namespace streetsim::field
