// The Gaussian parameter store: the one host-side representation of a 3DGS scene.
//
// Structure of arrays, raw (pre-activation) parameters exactly as 3DGS optimises them:
// log-scales, unnormalised rotation quaternions (w, x, y, z), opacity logits and SH coefficients.
// Backends copy this once into their own memory (render/engine.h: Engine::Upload).
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "absl/status/status.h"

namespace streetsim {

// Number of SH coefficients per colour channel for a degree (0..3): (degree + 1)^2.
constexpr int ShCoeffsForDegree(int degree) { return (degree + 1) * (degree + 1); }
inline constexpr int kMaxShDegree = 3;

struct GaussianStore {
  int sh_degree = 0;  // 0..3

  std::vector<float> means;           // [N*3] x, y, z in world metres
  std::vector<float> log_scales;      // [N*3] log of per-axis standard deviation (metres)
  std::vector<float> rotations;       // [N*4] w, x, y, z (normalised at use)
  std::vector<float> opacity_logits;  // [N]   sigmoid gives opacity
  // [N * K * 3], K = ShCoeffsForDegree(sh_degree); coefficient-major per Gaussian:
  // sh[(i*K + k)*3 + c]. k = 0 is the DC term.
  std::vector<float> sh;
  // [N*3] or empty. Carried only so that PLY round trips are lossless; rendering ignores them.
  std::vector<float> normals;

  size_t size() const { return opacity_logits.size(); }
  int sh_coeffs() const { return ShCoeffsForDegree(sh_degree); }

  // Resizes every array for n Gaussians at the current sh_degree (normals only if present).
  void Resize(size_t n);

  // Checks array sizes agree and every value is finite; rotations must not be all zero.
  absl::Status Validate() const;
};

}  // namespace streetsim
