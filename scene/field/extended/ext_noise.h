// ε of the extended field's VAE (extended_config.h): N(0, 1) as a pure function of (seed, Gaussian
// index, latent index) — splitmix64 -> two uniforms -> Box-Muller, in double — so that a backward
// recomputes its forward's ε on any thread, and the Vulkan field (which draws it on the host per
// batch) uses the very same numbers as the cpu.
#pragma once

#include <cmath>
#include <cstdint>

namespace streetsim::field::internal {

inline uint64_t SplitMix(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}
inline double Normal(uint64_t seed, uint64_t g, uint64_t i) {
  const uint64_t h1 = SplitMix(seed ^ SplitMix(g * 0x100000001b3ull + i));
  const uint64_t h2 = SplitMix(h1);
  const double u1 = (static_cast<double>(h1 >> 11) + 0.5) * 0x1.0p-53;
  const double u2 = static_cast<double>(h2 >> 11) * 0x1.0p-53;
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
}

}  // namespace streetsim::field::internal
