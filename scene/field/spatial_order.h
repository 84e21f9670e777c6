// A cache-friendly evaluation order: Gaussians sorted along a Morton (Z-order) curve of their
// normalised position, so that consecutive rows sample neighbouring texels of every plane. The
// field's passes cost mostly cache misses on the large planes (512 x 512 x 32 floats = 32 MiB
// each) when rows come in random order.
#pragma once

#include <cstdint>
#include <vector>

#include "render/common/thread_pool.h"
#include "scene/field/deformation_field.h"

namespace streetsim::field {

// Row indices of `rows` (all n Gaussians when null) sorted by the Morton code of their position
// in the AABB (10 bits per axis; positions outside are clamped onto it).
std::vector<uint32_t> SpatialOrder(const FieldAabb& aabb, const float* means, size_t n, const uint32_t* rows,
                                   ThreadPool& pool);

}  // namespace streetsim::field
