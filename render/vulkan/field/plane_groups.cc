#include "render/vulkan/field/plane_groups.h"

#include <algorithm>

#include "absl/strings/str_cat.h"

namespace streetsim::field {

size_t PlaneGroups::largest() const {
  size_t m = 0;
  for (size_t g = 0; g < begin.size(); ++g) m = std::max(m, end[g] - begin[g]);
  return m;
}

absl::StatusOr<PlaneGroups> PackPlaneGroups(const FieldLayout& layout, size_t group_limit) {
  PlaneGroups pg;
  const int C = layout.channels;
  for (const PlaneInfo& pi : layout.planes) {
    const size_t bytes = pi.size(C) * sizeof(float);
    if (bytes > group_limit) {
      return absl::FailedPreconditionError(absl::StrCat("vulkan field: a ", pi.width, " x ", pi.height, " x ", C,
                                                        " plane (", bytes, " B) exceeds the device's buffer range ",
                                                        group_limit, " B"));
    }
    if (pg.begin.empty() || (pi.offset + pi.size(C) - pg.begin.back()) * sizeof(float) > group_limit) {
      pg.begin.push_back(pi.offset);
      pg.end.push_back(pi.offset);
    }
    pg.end.back() = pi.offset + pi.size(C);
    pg.table.insert(pg.table.end(), {static_cast<uint32_t>(pg.begin.size() - 1),
                                     static_cast<uint32_t>(pi.offset - pg.begin.back()),
                                     static_cast<uint32_t>(pi.width), static_cast<uint32_t>(pi.height)});
  }
  if (pg.begin.size() > static_cast<size_t>(kMaxPlaneBuffers)) {
    return absl::FailedPreconditionError(absl::StrCat("vulkan field: the planes need ", pg.begin.size(),
                                                      " buffers of at most ", group_limit, " B, the kernels bind ",
                                                      kMaxPlaneBuffers));
  }
  return pg;
}

}  // namespace streetsim::field
