// The extended-field counterpart of moving_field.h for the server tests: the modules of `config`
// (default: every module, ExtendedFieldConfig::AllOn()'s small sizes) on a MovingField base, with the gate opened and the decoder's last
// layers drawn at random (both start at 0), so that the modules and the decoder's Δscale /
// Δrotation / Δopacity change the scene and vary with time.
#pragma once

#include <cstdint>
#include <random>
#include <utility>

#include <gtest/gtest.h>

#include "scene/field/extended/extended_field.h"

namespace streetsim::testing {

inline field::ExtendedField MovingExtension(field::DeformationField base, uint64_t seed,
                                            const field::ExtendedFieldConfig& config = field::ExtendedFieldConfig::AllOn()) {
  absl::StatusOr<field::ExtendedField> f = field::ExtendedField::Create(std::move(base), config, seed);
  EXPECT_TRUE(f.ok()) << f.status();
  const field::ExtendedLayout& L = f->layout();
  std::vector<float>& p = f->mutable_params();
  if (L.has_gate) std::fill_n(p.begin() + L.gate_offset, L.model_dim, 0.5f);
  std::mt19937_64 rng(seed + 17);
  auto draw = [&](const field::nn::LinearSpec& s, float a) {
    std::uniform_real_distribution<float> u(-a, a);
    for (size_t i = 0; i < size_t(s.in) * s.out; ++i) p[s.w_offset + i] = u(rng);
  };
  draw(L.scale2, 0.1f);
  draw(L.rot2, 0.05f);
  draw(L.op2, 0.1f);
  return std::move(*f);
}

}  // namespace streetsim::testing
