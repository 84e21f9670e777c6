#include "render/vulkan/field/vulkan_deformed_scene.h"

#include <span>

#include "absl/strings/str_cat.h"

namespace streetsim::field {

absl::Status VulkanDeformScene(VulkanField& vf, const DeformationField& field, double time_coord,
                               const CanonicalView& c, ThreadPool& pool, DeformedScene* out) {
  if (c.n > 0 && (!c.means || !c.sh)) return absl::InvalidArgumentError("VulkanDeformScene: null canonical arrays");
  if (vf.layout().total != field.layout().total) {
    return absl::InvalidArgumentError("VulkanDeformScene: the Vulkan field has another layout");
  }
  const size_t n = c.n;
  out->time_coord = time_coord;
  if (absl::Status s = vf.Forward(field.QueryAtCoordinate(time_coord), std::span<const float>(c.means, n * 3),
                                  &out->dx, &out->dsh);
      !s.ok()) {
    return s;
  }
  ApplyDeformation(c, pool, out);
  return absl::OkStatus();
}

absl::StatusOr<DeformLosses> VulkanDeformBackward(VulkanField& vf, const DeformationField& field,
                                                  const CanonicalView& c, const DeformedScene& d, int active_degree,
                                                  const FieldHyper& h, ThreadPool& pool, GaussianGrads* grads,
                                                  std::vector<float>* d_field, std::vector<float>* scratch) {
  const size_t n = c.n;
  if (active_degree < 0 || active_degree > 3) {
    return absl::InvalidArgumentError(absl::StrCat("VulkanDeformBackward: SH degree ", active_degree));
  }
  const int ka3 = ShCoeffsForDegree(active_degree) * 3;
  if (grads->means.size() != n * 3 || grads->sh.size() != n * ka3 || d.dx.size() != n * 3 ||
      d.dsh.size() != n * kShOutputs) {
    return absl::InvalidArgumentError(absl::StrCat("VulkanDeformBackward: sizes disagree (", n,
                                                   " Gaussians, grads ", grads->means.size() / 3, ", deformed ",
                                                   d.dx.size() / 3, ")"));
  }
  const FieldQuery query = field.QueryAtCoordinate(d.time_coord);
  if (d_field == nullptr && n == 0) {  // the device gradient must still be replaced by 0
    if (absl::Status s = vf.BackwardOnDevice(query, {}, {}, {}, {}); !s.ok()) return s;
    return DeformLosses{};
  }
  if (d_field != nullptr && d_field->size() != field.layout().total) d_field->assign(field.layout().total, 0.0f);
  if (n == 0) return DeformLosses{};
  scratch->resize(n * (3 + kShOutputs));
  float* g_dx = scratch->data();
  float* g_dsh = g_dx + n * 3;
  DeformLosses losses = SparsityGradients(d.dx, d.dsh, ka3, h, *grads, pool, g_dx, g_dsh);
  // grads->means already holds the identity path; the field adds the sampling-position path.
  const std::span<const float> means(c.means, n * 3), d_dx(g_dx, n * 3), d_dsh(g_dsh, n * kShOutputs);
  if (absl::Status s = d_field ? vf.Backward(query, means, d_dx, d_dsh, *d_field, grads->means)
                               : vf.BackwardOnDevice(query, means, d_dx, d_dsh, grads->means);
      !s.ok()) {
    return s;
  }
  return losses;
}

}  // namespace streetsim::field
