// field_ext.bin: the extension of an extended field beside field.bin (which keeps S3Gaussian's
// planes and MLP in its unchanged format, so every reader of field.bin still works), and the
// extension's part of fine-stage checkpoints (with its Adam moments). Binary, little-endian,
// versioned, checksummed, written to PATH.tmp and renamed (docs/field.md "Extended field"):
//   "SSFLDEXT", u32 version (1; 2 with the VAE's dilated branch; 3 with the decoder's Δlog-scale
//   bound), u32 flags (bit 0: Adam moments follow), u8 encoder, vae, temporal, attention, gru,
//   decoder, i32 heads, vae_latent, gru_hidden, window_k, fourier_frequencies, encoder_layers,
//   activation, [version >= 2: i32 vae_dilation], [version 3: f32 decoder_max_dlog_scale],
//   f64 window_dt, f64 kl_weight,
//   i32 kl_warmup_iterations, i32 base feature dim, i32 base width,
//   u64 base checksum (FNV-1a of field.bin's parameters: a field_ext.bin never pairs with another
//   run's field.bin), u64 count, f32 params[count], [i64 Adam step, f32 m, f32 v], u64 checksum.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/field_adam.h"

namespace streetsim::field {

inline constexpr char kExtendedFieldFileName[] = "field_ext.bin";  // beside field.bin

// The checksum field_ext.bin records of its base field's parameters.
uint64_t BaseParamsChecksum(const std::vector<float>& params);

absl::Status SaveExtendedField(const ExtendedField& field, const std::string& path);
// The extension of `base` (field.bin's field; checked against the recorded checksum).
absl::StatusOr<ExtendedField> LoadExtendedField(const std::string& path, DeformationField base);

struct ExtAdamState {
  std::vector<float> m, v;
  int64_t step = 0;
};
absl::Status SaveExtendedCheckpoint(const ExtendedField& field, const ExtAdamState& adam, const std::string& path);
absl::StatusOr<ExtendedField> LoadExtendedCheckpoint(const std::string& path, DeformationField base,
                                                     ExtAdamState* adam);

}  // namespace streetsim::field
