// Configuration and parameter layout of S3Gaussian's spatio-temporal deformation field
// (../shared/docs/s3gaussian-spec.md section 3; docs/field.md).
//
// All field parameters live in one flat array (float for training and serving, double for gradient
// checks): first every HexPlane plane (the Adam group "grid"), then the MLP (the group
// "deformation"). FieldLayout says where each piece lives; gradients use the same layout.
#pragma once

#include <cstddef>
#include <vector>

#include "absl/status/status.h"

namespace streetsim::field {

inline constexpr int kPlanesPerLevel = 6;
inline constexpr int kShCoeffs = 16;           // SH degree 3: every coefficient is deformed
inline constexpr int kShOutputs = kShCoeffs * 3;
// Coordinate pairs (i, j) of the 6 planes, in the spec's (lexicographic) order:
// xy, xz, xt, yz, yt, zt. Coordinate 3 is time.
inline constexpr int kPlaneCoords[kPlanesPerLevel][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};
inline constexpr bool PlaneHasTime(int c) { return kPlaneCoords[c][1] == 3; }

struct FieldConfig {
  // HexPlane (spec 3.1): level l has spatial resolution base_resolution * multires[l] and time
  // resolution time_resolution; `channels` features per texel.
  int channels = 32;
  int base_resolution = 64;
  std::vector<int> multires = {1, 2, 4, 8};
  int time_resolution = 25;
  // MLP (spec 3.2): trunk Linear(levels * channels -> width), heads width -> width -> {3, 48}.
  int width = 64;
  // Spatial-plane init U(lo, hi); time planes start at 1.
  float plane_init_lo = 0.1f, plane_init_hi = 0.5f;
  // Departure from S3Gaussian (method.md section 1): the log's time range maps to the full [-1, 1]
  // of the time axis. false = S3Gaussian's t in [0, 1] (only the upper half of the axis is used).
  bool full_time_range = true;
  // Departure from S3Gaussian behind a switch (`streetsim train --field-init zero-heads`): the last
  // Linear of the Δposition and ΔSH heads starts at zero, so that the fine stage starts exactly
  // from the static model instead of moving every Gaussian by the random heads' output (about
  // ±0.1 m and a colour shift). Not the default: Δ = W h then grows only at the heads' learning
  // rate, and on KITTI it learned motion later and ended 0.6-0.8 dB lower after 500 fine
  // iterations (docs/training.md "Field init"). false = the spec's init (Xavier weights, PyTorch
  // biases on every layer).
  bool zero_init_heads = false;

  int num_levels() const { return static_cast<int>(multires.size()); }
  int feature_dim() const { return num_levels() * channels; }
  absl::Status Validate() const;

  // Spec sizes with S3Gaussian's time mapping (for weight compatibility).
  static FieldConfig S3Gaussian() {
    FieldConfig c;
    c.full_time_range = false;
    return c;
  }
};

struct PlaneInfo {
  size_t offset = 0;  // into the flat parameters; texel (row v, column u) channel k at
                      // offset + (v * width + u) * channels + k (channels contiguous per texel)
  int width = 0;      // resolution of the plane's first coordinate (u)
  int height = 0;     // resolution of the plane's second coordinate (v; time for space-time planes)
  int level = 0;
  int plane = 0;      // 0..5, kPlaneCoords
  size_t size(int channels) const { return static_cast<size_t>(width) * height * channels; }
};

// A Linear layer y = W x + b, W row-major [out x in] (PyTorch's weight layout).
struct DenseInfo {
  size_t w_offset = 0, b_offset = 0;
  int out = 0, in = 0;
};

struct FieldLayout {
  int channels = 0;
  int num_levels = 0;
  int width = 0;
  std::vector<PlaneInfo> planes;  // level-major: planes[level * 6 + plane]
  size_t grid_size = 0;           // parameters [0, grid_size) are planes
  DenseInfo trunk, pos1, pos2, sh1, sh2;
  size_t total = 0;

  int feature_dim() const { return num_levels * channels; }
  // Spatial resolution of a level (x, y, z) and the time resolution.
  std::vector<int> level_resolution;  // [num_levels]
  int time_resolution = 0;

  static FieldLayout Make(const FieldConfig& config);
};

}  // namespace streetsim::field
