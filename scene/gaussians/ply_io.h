// INRIA 3DGS PLY layout: read and write.
//
// Properties (all float, binary little endian): x y z [nx ny nz] f_dc_0..2 [f_rest_0..M-1] opacity
// scale_0..2 rot_0..3, with f_rest channel-major (all of red's higher-order coefficients, then
// green's, then blue's). M = 3 * ((d+1)^2 - 1) gives the SH degree d (0..3).
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

struct PlyReadOptions {
  // Refuse files claiming more Gaussians than this (guards against absurd counts before allocating).
  size_t max_gaussians = 50'000'000;
};

absl::StatusOr<GaussianStore> ReadGaussianPly(const std::string& path,
                                              const PlyReadOptions& options = {});
// Parses an in-memory PLY file (the same rules as ReadGaussianPly).
absl::StatusOr<GaussianStore> ParseGaussianPly(std::string_view bytes,
                                               const PlyReadOptions& options = {});

// Writes atomically (temp file + rename). Normals are written only when the store has them.
absl::Status WriteGaussianPly(const GaussianStore& store, const std::string& path);
// Requires store.Validate().ok() (array sizes are trusted, not checked).
std::string SerializeGaussianPly(const GaussianStore& store);

// The same with one extra float vertex property, `reflectance` (per Gaussian, [0, 1]; a trained
// scene's LiDAR reflectance, docs/lidar.md), after the 3DGS properties; null: none. INRIA viewers
// ignore it; ReadGaussianPly accepts and skips it (train::ReadPlyReflectance reads it).
// InvalidArgument when the size differs from the store's or a value is outside [0, 1].
absl::Status WriteGaussianPly(const GaussianStore& store, const std::string& path,
                              const std::vector<float>* reflectance);
std::string SerializeGaussianPly(const GaussianStore& store, const std::vector<float>* reflectance);

}  // namespace streetsim
