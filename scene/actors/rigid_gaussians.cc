#include "scene/actors/rigid_gaussians.h"

#include <cmath>

#include <Eigen/Dense>

#include "render/common/projection_math.h"

namespace streetsim::actors {
namespace {

// Directions spread over the sphere (a Fibonacci lattice): well conditioned for every band.
constexpr int kSamples = 32;

Eigen::Vector3d SampleDirection(int j) {
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  const double z = 1.0 - 2.0 * (j + 0.5) / kSamples;
  const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
  return Eigen::Vector3d(r * std::cos(golden * j), r * std::sin(golden * j), z);
}

}  // namespace

ShRotation::ShRotation(const Eigen::Matrix3d& R) {
  // Band l's coefficients c' satisfy sum_k c'_k Y_k(d) = sum_k c_k Y_k(R^T d) for every d.
  Eigen::MatrixXd A(kSamples, 16), B(kSamples, 16);
  for (int j = 0; j < kSamples; ++j) {
    const Eigen::Vector3d d = SampleDirection(j);
    const Eigen::Vector3d back = R.transpose() * d;
    double a[16], b[16];
    projection::ShBasis<double>(3, d.x(), d.y(), d.z(), a);
    projection::ShBasis<double>(3, back.x(), back.y(), back.z(), b);
    for (int k = 0; k < 16; ++k) {
      A(j, k) = a[k];
      B(j, k) = b[k];
    }
  }
  band_[0] = Eigen::MatrixXd::Identity(1, 1);
  for (int l = 1; l <= 3; ++l) {
    const int first = l * l, width = 2 * l + 1;
    const Eigen::MatrixXd Al = A.middleCols(first, width), Bl = B.middleCols(first, width);
    band_[l] = Al.colPivHouseholderQr().solve(Bl);
  }
}

void ShRotation::Apply(int degree, float* sh) const {
  for (int l = 1; l <= degree; ++l) {
    const int first = l * l, width = 2 * l + 1;
    for (int c = 0; c < 3; ++c) {
      double in[7], out[7];
      for (int k = 0; k < width; ++k) in[k] = sh[(first + k) * 3 + c];
      for (int r = 0; r < width; ++r) {
        out[r] = 0;
        for (int k = 0; k < width; ++k) out[r] += band_[l](r, k) * in[k];
      }
      for (int k = 0; k < width; ++k) sh[(first + k) * 3 + c] = static_cast<float>(out[k]);
    }
  }
}

void TransformGaussians(const Eigen::Isometry3d& T, GaussianStore* g, size_t begin, size_t end) {
  const Eigen::Matrix3d R = T.rotation();
  const Eigen::Quaterniond qR(R);
  const ShRotation sh_rotation(R);
  const int K = g->sh_coeffs();
  for (size_t i = begin; i < end; ++i) {
    float* m = &g->means[i * 3];
    const Eigen::Vector3d p = T * Eigen::Vector3d(m[0], m[1], m[2]);
    for (int a = 0; a < 3; ++a) m[a] = static_cast<float>(p[a]);
    float* q = &g->rotations[i * 4];
    // The store keeps unnormalised quaternions: the product keeps their norm, as 3DGS expects.
    const Eigen::Quaterniond r = qR * Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
    q[0] = static_cast<float>(r.w());
    q[1] = static_cast<float>(r.x());
    q[2] = static_cast<float>(r.y());
    q[3] = static_cast<float>(r.z());
    if (g->sh_degree > 0) sh_rotation.Apply(g->sh_degree, &g->sh[i * K * 3]);
    if (!g->normals.empty()) {
      float* n = &g->normals[i * 3];
      const Eigen::Vector3d v = R * Eigen::Vector3d(n[0], n[1], n[2]);
      for (int a = 0; a < 3; ++a) n[a] = static_cast<float>(v[a]);
    }
  }
}

void AppendRows(const GaussianStore& from, const uint32_t* rows, size_t n, GaussianStore* to) {
  const size_t base = to->size();
  to->Resize(base + n);
  const int K = from.sh_coeffs();
  for (size_t j = 0; j < n; ++j) {
    const size_t i = rows[j], o = base + j;
    std::copy_n(&from.means[i * 3], 3, &to->means[o * 3]);
    std::copy_n(&from.log_scales[i * 3], 3, &to->log_scales[o * 3]);
    std::copy_n(&from.rotations[i * 4], 4, &to->rotations[o * 4]);
    to->opacity_logits[o] = from.opacity_logits[i];
    std::copy_n(&from.sh[i * K * 3], K * 3, &to->sh[o * K * 3]);
    if (!to->normals.empty()) {
      if (from.normals.empty()) {
        std::fill_n(&to->normals[o * 3], 3, 0.0f);
      } else {
        std::copy_n(&from.normals[i * 3], 3, &to->normals[o * 3]);
      }
    }
  }
}

}  // namespace streetsim::actors
