#include "scene/field/vulkan/vulkan_deformed_scene.h"

#include <cmath>
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
  out->means.resize(n * 3);
  out->sh.resize(n * kShOutputs);
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b * 3; i < e * 3; ++i) out->means[i] = c.means[i] + out->dx[i];
    for (int64_t i = b * kShOutputs; i < e * kShOutputs; ++i) out->sh[i] = c.sh[i] + out->dsh[i];
  });
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
  if (d_field->size() != field.layout().total) d_field->assign(field.layout().total, 0.0f);
  DeformLosses losses;
  if (n == 0) return losses;
  // As DeformBackward: dL/dΔx = dL/dxyz_t + sparsity; dL/dΔSH = dL/dsh_t (active coefficients) +
  // sparsity (keep the two in step).
  scratch->resize(n * (3 + kShOutputs));
  float* g_dx = scratch->data();
  float* g_dsh = g_dx + n * 3;
  const float cdx = static_cast<float>(h.lambda_dx / (3.0 * n));
  const float cdsh = static_cast<float>(h.lambda_dsh / (double(kShOutputs) * n));
  const int nt = pool.num_threads();
  std::vector<double> sum_dx(nt, 0.0), sum_dsh(nt, 0.0);
  auto sign = [](float x) { return static_cast<float>((x > 0) - (x < 0)); };
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int tid) {
    double sx = 0, ss = 0;
    for (int64_t i = b * 3; i < e * 3; ++i) {
      sx += std::abs(d.dx[i]);
      g_dx[i] = grads->means[i] + cdx * sign(d.dx[i]);
    }
    for (int64_t i = b; i < e; ++i) {
      for (int k = 0; k < kShOutputs; ++k) {
        const float v = d.dsh[i * kShOutputs + k];
        ss += std::abs(v);
        g_dsh[i * kShOutputs + k] = (k < ka3 ? grads->sh[i * ka3 + k] : 0.0f) + cdsh * sign(v);
      }
    }
    sum_dx[tid] += sx;
    sum_dsh[tid] += ss;
  });
  for (int t = 0; t < nt; ++t) {
    losses.dx_l1 += sum_dx[t];
    losses.dsh_l1 += sum_dsh[t];
  }
  losses.dx_l1 /= 3.0 * n;
  losses.dsh_l1 /= double(kShOutputs) * n;
  losses.weighted = h.lambda_dx * losses.dx_l1 + h.lambda_dsh * losses.dsh_l1;
  // grads->means already holds the identity path; the field adds the sampling-position path.
  if (absl::Status s = vf.Backward(field.QueryAtCoordinate(d.time_coord), std::span<const float>(c.means, n * 3),
                                   std::span<const float>(g_dx, n * 3), std::span<const float>(g_dsh, n * kShOutputs),
                                   *d_field, grads->means);
      !s.ok()) {
    return s;
  }
  return losses;
}

}  // namespace streetsim::field
