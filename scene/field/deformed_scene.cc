#include "scene/field/deformed_scene.h"

#include <cmath>

#include "absl/strings/str_cat.h"
#include "scene/field/huge_pages.h"

namespace streetsim::field {

absl::Status DeformScene(const DeformationField& field, double time_coord, const CanonicalView& c, ThreadPool& pool,
                         FieldWorkspace& ws, DeformedScene* out) {
  if (c.n > 0 && (!c.means || !c.sh)) return absl::InvalidArgumentError("DeformScene: null canonical arrays");
  const size_t n = c.n;
  out->time_coord = time_coord;
  out->dx.resize(n * 3);
  out->dsh.resize(n * kShOutputs);
  FieldForward<float>(field.layout(), field.params().data(), field.QueryAtCoordinate(time_coord), c.means, nullptr,
                      n, out->dx.data(), out->dsh.data(), pool, ws);
  ApplyDeformation(c, pool, out);
  return absl::OkStatus();
}

void ApplyDeformation(const CanonicalView& c, ThreadPool& pool, DeformedScene* out) {
  const size_t n = c.n;
  out->means.resize(n * 3);
  out->sh.resize(n * kShOutputs);
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int) {
    for (int64_t i = b * 3; i < e * 3; ++i) out->means[i] = c.means[i] + out->dx[i];
    for (int64_t i = b * kShOutputs; i < e * kShOutputs; ++i) out->sh[i] = c.sh[i] + out->dsh[i];
  });
}

GaussianParamsView DeformedParamsView(const GaussianParamsView& canonical, const DeformedScene& deformed) {
  GaussianParamsView v = canonical;
  v.means = deformed.means.data();
  v.sh = deformed.sh.data();
  v.sh_stride = kShCoeffs;
  return v;
}

DeformLosses SparsityGradients(const std::vector<float>& dx, const std::vector<float>& dsh, int ka3,
                               const FieldHyper& h, const GaussianGrads& grads, ThreadPool& pool, float* g_dx,
                               float* g_dsh) {
  const size_t n = dx.size() / 3;
  DeformLosses losses;
  if (n == 0) return losses;
  const float cdx = static_cast<float>(h.lambda_dx / (3.0 * n));
  const float cdsh = static_cast<float>(h.lambda_dsh / (double(kShOutputs) * n));
  const int nt = pool.num_threads();
  std::vector<double> sum_dx(nt, 0.0), sum_dsh(nt, 0.0);
  auto sign = [](float x) { return static_cast<float>((x > 0) - (x < 0)); };
  pool.ParallelFor(static_cast<int64_t>(n), 8192, [&](int64_t b, int64_t e, int tid) {
    double sx = 0, ss = 0;
    for (int64_t i = b * 3; i < e * 3; ++i) {
      sx += std::abs(dx[i]);
      g_dx[i] = grads.means[i] + cdx * sign(dx[i]);
    }
    for (int64_t i = b; i < e; ++i) {
      for (int k = 0; k < kShOutputs; ++k) {
        const float v = dsh[i * kShOutputs + k];
        ss += std::abs(v);
        g_dsh[i * kShOutputs + k] = (k < ka3 ? grads.sh[i * ka3 + k] : 0.0f) + cdsh * sign(v);
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
  return losses;
}

absl::StatusOr<DeformLosses> DeformBackward(const DeformationField& field, const CanonicalView& c,
                                            const DeformedScene& d, int active_degree, const FieldHyper& h,
                                            ThreadPool& pool, FieldWorkspace& ws, GaussianGrads* grads,
                                            std::vector<float>* d_field) {
  const size_t n = c.n;
  if (active_degree < 0 || active_degree > 3) {
    return absl::InvalidArgumentError(absl::StrCat("DeformBackward: SH degree ", active_degree));
  }
  const int ka3 = ShCoeffsForDegree(active_degree) * 3;
  if (grads->means.size() != n * 3 || grads->sh.size() != n * ka3 || d.dx.size() != n * 3 ||
      d.dsh.size() != n * kShOutputs) {
    return absl::InvalidArgumentError(absl::StrCat("DeformBackward: sizes disagree (", n, " Gaussians, grads ",
                                                   grads->means.size() / 3, ", deformed ", d.dx.size() / 3, ")"));
  }
  if (d_field->size() != field.layout().total) AssignOnHugePages(d_field, field.layout().total, 0.0f);
  if (n == 0) return DeformLosses{};
  std::vector<float>& g_dx = ws.d_dx;
  std::vector<float>& g_dsh = ws.d_dsh;
  g_dx.resize(n * 3);
  g_dsh.resize(n * kShOutputs);
  DeformLosses losses = SparsityGradients(d.dx, d.dsh, ka3, h, *grads, pool, g_dx.data(), g_dsh.data());
  // grads->means already holds the identity path; the field adds the sampling-position path.
  FieldBackward<float>(field.layout(), field.params().data(), field.QueryAtCoordinate(d.time_coord), c.means, n,
                       g_dx.data(), g_dsh.data(), d_field->data(), grads->means.data(), pool, ws);
  return losses;
}

}  // namespace streetsim::field
