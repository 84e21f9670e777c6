// Glue between the field and the trainer (spec 3.3, 5): deform the canonical Gaussians at one
// time, and back-propagate the rendered scene's gradients (render/engine.h GaussianGrads) to the
// field parameters and the canonical parameters.
//
//   xyz_t = xyz + Δx(xyz, t)    sh_t = sh + ΔSH(xyz, t)    (scale, rotation, opacity unchanged)
//
// Fine-stage loss terms that need the deformations are added here: lambda_dx * mean |Δx| and
// lambda_dsh * mean |ΔSH| (means over N x 3 and N x 48).
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_adam.h"

namespace streetsim::field {

// The canonical parameters the field acts on, in the trainer's layout (SH degree 3:
// sh[(i * 16 + k) * 3 + c]).
struct CanonicalView {
  size_t n = 0;
  const float* means = nullptr;  // [n*3]
  const float* sh = nullptr;     // [n*48]
};

struct DeformedScene {
  double time_coord = 0;
  std::vector<float> dx;     // [n*3]
  std::vector<float> dsh;    // [n*48]
  std::vector<float> means;  // [n*3]  xyz + Δx
  std::vector<float> sh;     // [n*48] sh + ΔSH
};

// Evaluates the field at `time_coord` (DeformationField::TimeCoordinate) for every Gaussian.
absl::Status DeformScene(const DeformationField& field, double time_coord, const CanonicalView& canonical,
                         ThreadPool& pool, FieldWorkspace& ws, DeformedScene* out);

// The second half of DeformScene (and of VulkanDeformScene), once out->dx and out->dsh hold the
// field's output for the n Gaussians of `canonical`: out->means and out->sh = canonical + Δ.
void ApplyDeformation(const CanonicalView& canonical, ThreadPool& pool, DeformedScene* out);

// `canonical` (the trainer's ParamsView at the active degree, sh_stride 16) with the deformed
// means and SH of `deformed` in place of the canonical ones, for Engine::UpdateSceneParams.
GaussianParamsView DeformedParamsView(const GaussianParamsView& canonical, const DeformedScene& deformed);

struct DeformLosses {
  double dx_l1 = 0;   // mean |Δx|
  double dsh_l1 = 0;  // mean |ΔSH|
  double weighted = 0;
};

// The Δ sparsity terms of every field's backward (DeformBackward, VulkanDeformBackward,
// DeformBackwardExt), from the Δx [n*3] and ΔSH [n*48] the forward produced:
// dL/dΔx = dL/dxyz_t + sparsity into g_dx [n*3], dL/dΔSH = dL/dsh_t (the ka3 = active SH
// coefficients x 3 of `grads`) + sparsity into g_dsh [n*48]; returns the mean |Δ| losses.
DeformLosses SparsityGradients(const std::vector<float>& dx, const std::vector<float>& dsh, int ka3,
                               const FieldHyper& hyper, const GaussianGrads& grads, ThreadPool& pool, float* g_dx,
                               float* g_dsh);

// Given `grads` of the rendered deformed scene (means [n*3], sh [n*Ka*3] at `active_degree`),
// adds dL/d(field parameters) (including the Δ sparsity terms) to d_field [layout.total] (a
// vector of another size is replaced by zeros on huge pages: pass an empty one the first time) and
// turns grads->means into dL/d(canonical means): the identity path plus the path through the
// field's sampling position. grads->sh needs no change (ΔSH is added, the SH gradient is the
// same); SH coefficients above the active degree get gradient only from the sparsity term,
// which acts on the field alone. `deformed` is the DeformScene result the render used.
absl::StatusOr<DeformLosses> DeformBackward(const DeformationField& field, const CanonicalView& canonical,
                                            const DeformedScene& deformed, int active_degree, const FieldHyper& hyper,
                                            ThreadPool& pool, FieldWorkspace& ws, GaussianGrads* grads,
                                            std::vector<float>* d_field);

}  // namespace streetsim::field
