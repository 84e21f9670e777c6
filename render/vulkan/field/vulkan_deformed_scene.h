// The trainer glue of scene/field/deformed_scene.h (DeformScene / DeformBackward: xyz_t = xyz + Δx,
// sh_t = sh + ΔSH, the Δ sparsity terms, canonical-mean gradient) with the field evaluated by a
// VulkanField. Same inputs, outputs and semantics as the cpu glue, so a trainer swaps one call
// for the other; after each host optimiser step the caller re-uploads the parameters
// (VulkanField::UpdateParams), or steps on the device (VulkanField::RegularizeAndStep).
// tests/field/vulkan_deformed_scene_test.cc checks it against the cpu glue.
#pragma once

#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "scene/field/deformed_scene.h"
#include "render/vulkan/field/vulkan_field.h"

namespace streetsim::field {

// As DeformScene; `field` supplies the AABB (the parameters are those last uploaded to `vf`).
absl::Status VulkanDeformScene(VulkanField& vf, const DeformationField& field, double time_coord,
                               const CanonicalView& canonical, ThreadPool& pool, DeformedScene* out);

// As DeformBackward (d_field: resized to layout.total with zeros when its size differs; gradients
// are added). d_field null: the parameter gradient stays on the device for
// VulkanField::RegularizeAndStep (VulkanField::BackwardOnDevice). `scratch` holds dL/dΔx and
// dL/dΔSH between calls (no allocation after the first).
absl::StatusOr<DeformLosses> VulkanDeformBackward(VulkanField& vf, const DeformationField& field,
                                                  const CanonicalView& canonical, const DeformedScene& deformed,
                                                  int active_degree, const FieldHyper& hyper, ThreadPool& pool,
                                                  GaussianGrads* grads, std::vector<float>* d_field,
                                                  std::vector<float>* scratch);

}  // namespace streetsim::field
