// Packing of a field's planes into up to kMaxPlaneBuffers storage buffers ("plane groups"), for the
// Vulkan kernels that bind them (field_planes.glsl): greedily in layout order, a plane never split,
// each group at most `group_limit_bytes` (a device's maxStorageBufferRange: 128 MiB on lavapipe,
// below the spec's 136 MiB of planes). Shared by VulkanField and VulkanExtendedField.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/field/field_config.h"

namespace streetsim::field {

inline constexpr int kMaxPlaneBuffers = 4;  // field_planes.glsl: bindings 0..3 (gradients 8..11)

struct PlaneGroups {
  // Group g holds the flat parameters [begin[g], end[g]).
  std::vector<size_t> begin, end;
  // Per plane (layout order): group, float offset in the group, width, height (field_planes.glsl).
  std::vector<uint32_t> table;
  size_t largest() const;  // floats of the largest group
};

// FailedPrecondition for a plane larger than the limit or more than kMaxPlaneBuffers groups.
absl::StatusOr<PlaneGroups> PackPlaneGroups(const FieldLayout& layout, size_t group_limit_bytes);

}  // namespace streetsim::field
