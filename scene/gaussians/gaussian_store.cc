#include "scene/gaussians/gaussian_store.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace streetsim {

void GaussianStore::Resize(size_t n) {
  means.resize(n * 3);
  log_scales.resize(n * 3);
  rotations.resize(n * 4);
  opacity_logits.resize(n);
  sh.resize(n * static_cast<size_t>(sh_coeffs()) * 3);
  if (!normals.empty()) normals.resize(n * 3);
}

namespace {
absl::Status CheckArray(const std::vector<float>& v, size_t expected, const char* name) {
  if (v.size() != expected) {
    return absl::InvalidArgumentError(
        absl::StrCat("Gaussian store: ", name, " has ", v.size(), " values, expected ", expected));
  }
  for (size_t i = 0; i < v.size(); ++i) {
    if (!std::isfinite(v[i])) {
      return absl::InvalidArgumentError(
          absl::StrCat("Gaussian store: ", name, "[", i, "] is not finite"));
    }
  }
  return absl::OkStatus();
}
}  // namespace

absl::Status GaussianStore::Validate() const {
  if (sh_degree < 0 || sh_degree > kMaxShDegree) {
    return absl::InvalidArgumentError(absl::StrCat("SH degree ", sh_degree, " not in 0..3"));
  }
  const size_t n = size();
  if (absl::Status s = CheckArray(means, n * 3, "means"); !s.ok()) return s;
  if (absl::Status s = CheckArray(log_scales, n * 3, "log_scales"); !s.ok()) return s;
  if (absl::Status s = CheckArray(rotations, n * 4, "rotations"); !s.ok()) return s;
  if (absl::Status s = CheckArray(opacity_logits, n, "opacity_logits"); !s.ok()) return s;
  if (absl::Status s = CheckArray(sh, n * sh_coeffs() * 3, "sh"); !s.ok()) return s;
  if (!normals.empty()) {
    if (absl::Status s = CheckArray(normals, n * 3, "normals"); !s.ok()) return s;
  }
  for (size_t i = 0; i < n; ++i) {
    const float* q = &rotations[i * 4];
    if (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-20f) {
      return absl::InvalidArgumentError(absl::StrCat("Gaussian store: rotation ", i, " is zero"));
    }
  }
  return absl::OkStatus();
}

}  // namespace streetsim
