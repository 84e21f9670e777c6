// The data and rows shared by the extended-field benches (field_ext_bench, field_vk_ext_bench):
// S3Gaussian's field at the spec's sizes over a 200 x 200 x 20 m AABB (time planes varied), n
// Gaussians uniformly random in it with random opacities, scales and rotations, random upstream
// gradients, and per table row the extended field with those modules and the views of a training
// pass at 2.5 s over the same arrays.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <random>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "scene/field/extended/extended_field.h"

namespace streetsim::bench {

// Benches only: prints the error and exits.
inline void CheckOrExit(const absl::Status& s) {
  if (!s.ok()) {
    std::fprintf(stderr, "%s\n", s.ToString().c_str());
    std::exit(1);
  }
}

// The table's rows: every module off (the ablation baseline), each module alone, pairs, all.
inline constexpr const char* kExtBenchRows[] = {
    "none", "encoder", "vae", "vae_dilated", "temporal", "attention", "gru", "decoder", "temporal,attention",
    "temporal,gru", "all", "all,vae_dilated"};

struct ExtBenchScene {
  explicit ExtBenchScene(field::DeformationField b) : base(std::move(b)) {}
  field::DeformationField base;
  size_t n = 0;
  std::vector<float> means, opacity, scales, rotations;
  std::vector<float> dx, dsh, ds, dr, dop;                       // outputs
  std::vector<float> gdx, gdsh, gds, gdr, gdop;                  // upstream gradients
  std::vector<float> d_base, d_means, d_op, d_sc, d_rot, d_ext;  // input gradients
};

inline ExtBenchScene MakeExtBenchScene(size_t n) {
  field::FieldAabb aabb;
  aabb.min[0] = -100, aabb.min[1] = -100, aabb.min[2] = -5;
  aabb.max[0] = 100, aabb.max[1] = 100, aabb.max[2] = 15;
  const field::FieldConfig bc;
  absl::StatusOr<field::DeformationField> base = field::DeformationField::Create(bc, aabb, {0, 5000000}, 1);
  CheckOrExit(base.status());
  ExtBenchScene s(*std::move(base));
  s.n = n;
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<float> u(-0.2f, 0.2f);
  for (const field::PlaneInfo& p : s.base.layout().planes) {
    if (!field::PlaneHasTime(p.plane)) continue;
    for (size_t i = 0; i < p.size(bc.channels); ++i) s.base.mutable_params()[p.offset + i] += u(rng);
  }
  s.means.resize(n * 3), s.opacity.resize(n), s.scales.resize(n * 3), s.rotations.resize(n * 4);
  for (size_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) {
      s.means[i * 3 + a] = std::uniform_real_distribution<float>(aabb.min[a], aabb.max[a])(rng);
      s.scales[i * 3 + a] = std::uniform_real_distribution<float>(-3, 0)(rng);
    }
    s.opacity[i] = u(rng) * 10;
    for (int a = 0; a < 4; ++a) s.rotations[i * 4 + a] = std::normal_distribution<float>()(rng);
  }
  s.dx.resize(n * 3), s.dsh.resize(n * field::kShOutputs), s.ds.resize(n * 3), s.dr.resize(n * 4), s.dop.resize(n);
  s.gdx.resize(n * 3), s.gdsh.resize(n * field::kShOutputs), s.gds.resize(n * 3), s.gdr.resize(n * 4);
  s.gdop.resize(n);
  for (auto* v : {&s.gdx, &s.gdsh, &s.gds, &s.gdr, &s.gdop})
    for (float& x : *v) x = u(rng);
  s.d_base.resize(s.base.layout().total), s.d_means.resize(n * 3), s.d_op.resize(n), s.d_sc.resize(n * 3);
  s.d_rot.resize(n * 4);
  return s;
}

// One row: the extended field with `modules` (window_dt 0.02) over the scene's base field, and the
// views of a training pass at 2.5 s (the decoder's outputs only with the decoder).
struct ExtBenchRow {
  explicit ExtBenchRow(field::ExtendedField f) : field(std::move(f)) {}
  field::ExtendedField field;
  field::ExtPass pass;
  field::ExtInputs<float> in;
  field::ExtOutputs<float> out;
  field::ExtOutputGrads<float> g;
  field::ExtInputGrads<float> gi;
};

inline ExtBenchRow MakeExtBenchRow(ExtBenchScene& s, const char* modules,
                                   int window_k = field::ExtendedFieldConfig{}.window_k) {
  absl::StatusOr<field::ExtendedFieldConfig> ec = field::ExtendedFieldConfig::WithModules(modules);
  CheckOrExit(ec.status());
  ec->window_k = window_k;
  ec->window_dt = 0.02;
  absl::StatusOr<field::ExtendedField> ef = field::ExtendedField::Create(s.base, *ec, 3);
  CheckOrExit(ef.status());
  ExtBenchRow r(*std::move(ef));
  r.pass.time_coord = r.field.base().TimeCoordinate(2500000);
  r.pass.training = true;
  r.in = {s.n, s.means.data(), s.opacity.data(), s.scales.data(), s.rotations.data()};
  const bool dec = ec->decoder;
  r.out = {s.dx.data(), s.dsh.data(), dec ? s.ds.data() : nullptr, dec ? s.dr.data() : nullptr,
           dec ? s.dop.data() : nullptr};
  r.g = {s.gdx.data(), s.gdsh.data(), s.gds.data(), s.gdr.data(), s.gdop.data()};
  s.d_ext.assign(r.field.layout().total(), 0.0f);
  r.gi = {s.d_base.data(), s.d_ext.data(), s.d_means.data(), s.d_op.data(), s.d_sc.data(), s.d_rot.data()};
  return r;
}

}  // namespace streetsim::bench
