// Training uploads for the vulkan engine: a parameter view
// (Engine::UpdateSceneParams) packed straight into one persistent staging
// buffer in the scene's device layout, in parallel, and copied with one
// submission. The generic path (a GaussianStore copy, full validation, a
// staging buffer allocated per array and one submit per chunk) took 69 ms of a
// 112 ms training step at 139k Gaussians on an H100 (docs/benchmarks.md,
// "Vulkan on a GPU").
#pragma once

#include <cstddef>

#include "absl/status/status.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

// Where each device array lives in the packed staging bytes: the geometry (12
// floats per Gaussian: mean, opacity logit, log-scales, pad, rotation) then
// each SH group.
struct ParamPackLayout {
  size_t n = 0;
  int sh_coeffs = 0;
  size_t geometry_bytes = 0;
  size_t sh_offset[kMaxShGroups] = {};
  size_t sh_bytes[kMaxShGroups] = {}; // 0: group unused at this degree
  size_t total_bytes = 0;
};
ParamPackLayout MakeParamPackLayout(size_t n, int sh_coeffs);

// Packs `params` into `out` (layout.total_bytes). InvalidArgument for a
// non-finite value or a zero rotation (what rendering needs; the same checks as
// the cpu backend's in-place update), in which case `out` holds a partial copy
// that must not be uploaded.
absl::Status PackParams(const GaussianParamsView &params,
                        const ParamPackLayout &layout, ThreadPool &pool,
                        std::byte *out);

} // namespace streetsim::vulkan
