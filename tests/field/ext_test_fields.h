// A small extended field with random Gaussians and loss weights, shared by the extended field's
// gradient check (ext_grad_check_test.cc) and the Vulkan extended field's test
// (vk_ext_field_test.cc): the problem, its model / inputs views, the per-module configs, and the
// gradient groups both report per line.
#pragma once

#include <cmath>
#include <cstdint>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "scene/field/extended/extended_field.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field::testing {

// Floats per Gaussian of each output: dx, dsh, dscale, drot, dopacity.
inline constexpr int kExtOut[5] = {3, kShOutputs, kDecoderScaleOutputs, kDecoderRotationOutputs,
                                   kDecoderOpacityOutputs};

template <typename T>
struct ExtValues {
  std::vector<T> base, ext, means, opacity, scales, rotations;
  std::vector<T> w[5];  // loss weights per output (the upstream gradients)
};

struct ExtProblem {
  FieldConfig bc = SmallConfig();
  FieldLayout BL;
  ExtendedFieldConfig ec;
  ExtendedLayout EL;
  // The same values in double and float (every value rounded to float, so that both passes see
  // the same numbers); a test that changes one changes the other.
  ExtValues<double> v;
  ExtValues<float> f;
  size_t n = 0;
  ExtPass pass;
  double kl_weight = 0.3;
};

template <typename To, typename From>
ExtValues<To> CastValues(const ExtValues<From>& v) {
  auto c = [](const std::vector<From>& x) { return std::vector<To>(x.begin(), x.end()); };
  ExtValues<To> out;
  out.base = c(v.base), out.ext = c(v.ext), out.means = c(v.means), out.opacity = c(v.opacity);
  out.scales = c(v.scales), out.rotations = c(v.rotations);
  for (int o = 0; o < 5; ++o) out.w[o] = c(v.w[o]);
  return out;
}

// SmallConfig's base field, `n` Gaussians (a quarter outside the AABB), extension parameters moved
// off the init (zero gate and decoder outputs), a training pass at `time_coord`.
inline ExtProblem MakeExtProblem(const ExtendedFieldConfig& ec, size_t n, double time_coord, uint64_t seed) {
  ExtProblem p;
  p.BL = FieldLayout::Make(p.bc);
  p.ec = ec;
  absl::StatusOr<ExtendedLayout> el = ExtendedLayout::Make(p.bc, ec);
  EXPECT_TRUE(el.ok()) << el.status();
  p.EL = *el;
  p.n = n;
  ExtValues<double>& v = p.v;
  v.base = RandomParams<double>(p.bc, p.BL, seed);
  InitExtendedParams(ec, p.EL, seed + 1, &v.ext);
  std::mt19937_64 rng(seed + 2);
  std::uniform_real_distribution<double> u(-0.4, 0.4);
  std::normal_distribution<double> g;
  for (double& x : v.ext) x += u(rng);
  v.means = RandomMeans<double>(n, n / 4, seed + 3);
  v.opacity.resize(n);
  v.scales.resize(n * 3);
  v.rotations.resize(n * 4);
  for (double& x : v.opacity) x = g(rng);
  for (double& x : v.scales) x = -1.5 + u(rng) * 2;
  for (double& x : v.rotations) x = g(rng);
  for (int o = 0; o < 5; ++o) {
    v.w[o].resize(n * kExtOut[o]);
    for (double& x : v.w[o]) x = g(rng);
  }
  p.f = CastValues<float>(v);
  v = CastValues<double>(p.f);
  p.pass.time_coord = time_coord;
  p.pass.training = true;
  p.pass.noise_seed = seed + 11;
  return p;
}

template <typename T>
ExtModel<T> ExtModelOf(const ExtProblem& p, const ExtValues<T>& v) {
  ExtModel<T> m;
  m.base_layout = &p.BL;
  m.base_params = v.base.data();
  m.config = &p.ec;
  m.layout = &p.EL;
  m.ext_params = v.ext.data();
  m.aabb = TestAabb();
  return m;
}

template <typename T>
ExtInputs<T> ExtInputsOf(const ExtProblem& p, const ExtValues<T>& v) {
  return {p.n, v.means.data(), v.opacity.data(), v.scales.data(), v.rotations.data()};
}

// AllOn()'s small sizes with only `module` on ("vae_dilated": the VAE with its dilated branch).
inline ExtendedFieldConfig OnlyModule(const std::string& module) {
  ExtendedFieldConfig c = ExtendedFieldConfig::AllOn();
  absl::StatusOr<ExtendedFieldConfig> only = ExtendedFieldConfig::WithModules(module);
  EXPECT_TRUE(only.ok()) << module;
  if (!only.ok()) return c;
  c.encoder = only->encoder, c.vae = only->vae, c.temporal = only->temporal;
  c.attention = only->attention, c.gru = only->gru, c.decoder = only->decoder;
  c.vae_dilation = only->vae_dilation;
  return c;
}

// Relative L2 difference of a against ref over the entries idx.
inline double RelDiff(const std::vector<double>& a, const std::vector<double>& ref, const std::vector<size_t>& idx) {
  double num = 0, den = 0;
  for (size_t i : idx) num += (a[i] - ref[i]) * (a[i] - ref[i]), den += ref[i] * ref[i];
  return den > 0 ? std::sqrt(num / den) : std::sqrt(num);
}

inline std::vector<size_t> All(size_t n) {
  std::vector<size_t> v(n);
  for (size_t i = 0; i < n; ++i) v[i] = i;
  return v;
}

// Which array of ExtValues (or of any struct with the same six arrays) a gradient group indexes.
enum class ExtArray { kBase, kExt, kMeans, kOpacity, kScales, kRotations };

template <typename S>
auto& ArrayOf(S& s, ExtArray a) {
  switch (a) {
    case ExtArray::kBase: return s.base;
    case ExtArray::kExt: return s.ext;
    case ExtArray::kMeans: return s.means;
    case ExtArray::kOpacity: return s.opacity;
    case ExtArray::kScales: return s.scales;
    case ExtArray::kRotations: break;
  }
  return s.rotations;
}

struct ExtGroup {
  std::string name;
  ExtArray array;
  std::vector<size_t> idx;
};

// The groups the tests report one line each for: spatial planes, time planes, S3Gaussian's MLP,
// one per module (block name prefix up to the first dot), the means, and with the encoder the
// opacity logits, log scales and rotations it reads.
inline std::vector<ExtGroup> ExtGroups(const ExtProblem& p) {
  ExtGroup sp{"spatial planes", ExtArray::kBase, {}}, tp{"time planes", ExtArray::kBase, {}};
  for (const PlaneInfo& pi : p.BL.planes)
    for (size_t i = 0; i < pi.size(p.BL.channels); ++i) (PlaneHasTime(pi.plane) ? tp : sp).idx.push_back(pi.offset + i);
  ExtGroup mlp{"s3gaussian mlp", ExtArray::kBase, {}};
  for (size_t i = p.BL.grid_size; i < p.BL.total; ++i) mlp.idx.push_back(i);
  std::vector<ExtGroup> groups = {sp, tp, mlp};
  std::map<std::string, std::vector<size_t>> by_module;
  for (const nn::NnParamBlock& b : p.EL.params.blocks()) {
    const std::string mod = b.name.substr(0, b.name.find('.'));
    for (size_t i = 0; i < b.count; ++i) by_module[mod].push_back(b.offset + i);
  }
  for (auto& [mod, idx] : by_module) groups.push_back({mod, ExtArray::kExt, idx});
  groups.push_back({"means", ExtArray::kMeans, All(p.n * 3)});
  if (p.ec.encoder) {
    groups.push_back({"opacity logits", ExtArray::kOpacity, All(p.n)});
    groups.push_back({"log scales", ExtArray::kScales, All(p.n * 3)});
    groups.push_back({"rotations", ExtArray::kRotations, All(p.n * 4)});
  }
  return groups;
}

}  // namespace streetsim::field::testing
