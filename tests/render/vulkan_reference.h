// A deliberately plain scalar 3DGS forward pass for the vulkan backend's tests: project with
// render/common/projection_math.h (float), sort visible Gaussians by (depth, index), bin into
// 16x16 tiles row-major, blend each pixel front to back with the 3DGS rules.
#pragma once

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "render/camera.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::testing {

struct ReferenceImage {
  int width = 0, height = 0;
  std::vector<float> rgb, depth, alpha, final_t;
  std::vector<uint32_t> n_contrib;
  size_t num_visible = 0;
  size_t num_tile_instances = 0;
};

ReferenceImage RenderReference(const GaussianStore& store, const PinholeCamera& camera,
                               const Eigen::Vector3f& background);

struct SceneOptions {
  int num_gaussians = 500;
  int sh_degree = 0;
  uint32_t seed = 1;
  // Adds Gaussians behind the camera, across the near plane, huge, tiny and near-transparent.
  bool hard_cases = true;
};
// Random Gaussians in front of a camera at the origin looking down +z.
GaussianStore MakeRandomScene(const SceneOptions& options);

// A camera at `T_world_from_cam` (identity: at the origin looking down +z).
PinholeCamera MakeCamera(int width, int height, double focal_px, double cx_offset_px = 0,
                         double cy_offset_px = 0);

}  // namespace streetsim::testing
