// field.bin: the field's parameters (and, in checkpoints, its Adam moments) on disk. Binary,
// little-endian, versioned, with a checksum; written to a temporary file and renamed into place
// so that a crash never leaves a partial file. Layout (docs/field.md):
//   "SSFIELD\0", u32 version, u32 flags (bit 0: Adam moments follow the parameters),
//   config (i32 channels, base_resolution, levels, multires[levels], time_resolution, width,
//   f32 init lo, hi, u8 full_time_range), f64 aabb min[3], max[3], i64 start_us, end_us,
//   u64 count, f32 params[count], [i64 adam step, f32 m[count], f32 v[count]], u64 checksum.
#pragma once

#include <string>

#include "absl/status/statusor.h"
#include "scene/field/deformation_field.h"
#include "scene/field/field_adam.h"

namespace streetsim::field {

inline constexpr char kFieldFileName[] = "field.bin";  // beside scene.ply in a scene directory

absl::Status SaveField(const DeformationField& field, const std::string& path);
// Reads either kind of file (moments, if any, are skipped).
absl::StatusOr<DeformationField> LoadField(const std::string& path);

struct FieldCheckpoint {
  DeformationField field;
  FieldAdamState adam;
};
absl::Status SaveFieldCheckpoint(const DeformationField& field, const FieldAdamState& adam, const std::string& path);
// Requires the moments.
absl::StatusOr<FieldCheckpoint> LoadFieldCheckpoint(const std::string& path);

}  // namespace streetsim::field
