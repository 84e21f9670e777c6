// A rigid motion applied to Gaussians: what moving an actor does to its Gaussians.
//
// Means are mapped by T, rotations composed with T's rotation, scales and opacities kept, and the
// view-dependent colour turned with the body: the rotated Gaussian seen from direction d shows
// what the original showed from R^T d. Each SH band is a rotation-invariant subspace, so a band's
// coefficients map through one (2l+1)x(2l+1) matrix, found exactly by least squares over sample
// directions (ShRotation) rather than by Wigner recurrences.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "scene/gaussians/gaussian_store.h"

namespace streetsim::actors {

// The per-band matrices for one rotation (bands 1..3; band 0 is invariant).
class ShRotation {
 public:
  explicit ShRotation(const Eigen::Matrix3d& R_new_from_old);
  // Turns one Gaussian's coefficients sh[k*3 + c] (K = ShCoeffsForDegree(degree)) in place.
  void Apply(int degree, float* sh) const;

 private:
  Eigen::MatrixXd band_[4];  // band_[l]: (2l+1)^2, new = band_[l] * old
};

// Applies T_new_from_old to rows [begin, end) of `g` in place.
void TransformGaussians(const Eigen::Isometry3d& T_new_from_old, GaussianStore* g, size_t begin, size_t end);
inline void TransformGaussians(const Eigen::Isometry3d& T_new_from_old, GaussianStore* g) {
  TransformGaussians(T_new_from_old, g, 0, g->size());
}

// Rows of `from` (in `rows` order) appended to `to` (same sh_degree; normals dropped when `to` has none).
void AppendRows(const GaussianStore& from, const uint32_t* rows, size_t n, GaussianStore* to);

}  // namespace streetsim::actors
