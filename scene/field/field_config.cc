#include "scene/field/field_config.h"

#include "absl/strings/str_cat.h"

namespace streetsim::field {

absl::Status FieldConfig::Validate() const {
  // Bounds keep the flat array well inside size_t and a corrupt file from asking for terabytes.
  if (channels < 1 || channels > 256) {
    return absl::InvalidArgumentError(absl::StrCat("field: channels ", channels, " not in [1, 256]"));
  }
  if (multires.empty() || multires.size() > 8) {
    return absl::InvalidArgumentError(absl::StrCat("field: ", multires.size(), " levels, want 1..8"));
  }
  for (int m : multires) {
    const long r = static_cast<long>(base_resolution) * m;
    if (m < 1 || base_resolution < 2 || r > 4096) {
      return absl::InvalidArgumentError(absl::StrCat("field: spatial resolution ", base_resolution, " x ", m,
                                                     " not in [2, 4096]"));
    }
  }
  if (time_resolution < 2 || time_resolution > 4096) {
    return absl::InvalidArgumentError(absl::StrCat("field: time resolution ", time_resolution, " not in [2, 4096]"));
  }
  if (width < 1 || width > 1024) {
    return absl::InvalidArgumentError(absl::StrCat("field: width ", width, " not in [1, 1024]"));
  }
  if (!(plane_init_lo <= plane_init_hi)) return absl::InvalidArgumentError("field: plane init lo > hi");
  return absl::OkStatus();
}

FieldLayout FieldLayout::Make(const FieldConfig& config) {
  FieldLayout L;
  L.channels = config.channels;
  L.num_levels = config.num_levels();
  L.width = config.width;
  L.time_resolution = config.time_resolution;
  size_t off = 0;
  for (int l = 0; l < L.num_levels; ++l) {
    const int r = config.base_resolution * config.multires[l];
    L.level_resolution.push_back(r);
    for (int c = 0; c < kPlanesPerLevel; ++c) {
      PlaneInfo p;
      p.level = l;
      p.plane = c;
      p.width = r;  // the first coordinate is always spatial
      p.height = PlaneHasTime(c) ? config.time_resolution : r;
      p.offset = off;
      off += p.size(L.channels);
      L.planes.push_back(p);
    }
  }
  L.grid_size = off;
  auto dense = [&](int out, int in) {
    DenseInfo d;
    d.out = out;
    d.in = in;
    d.w_offset = off;
    off += static_cast<size_t>(out) * in;
    d.b_offset = off;
    off += out;
    return d;
  };
  const int W = config.width;
  L.trunk = dense(W, L.feature_dim());
  L.pos1 = dense(W, W);
  L.pos2 = dense(3, W);
  L.sh1 = dense(W, W);
  L.sh2 = dense(kShOutputs, W);
  L.total = off;
  return L;
}

}  // namespace streetsim::field
