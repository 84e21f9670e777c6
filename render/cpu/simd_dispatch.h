// Which of the two builds of the cpu kernels (x86-64-v3 = AVX2, x86-64-v4 = AVX-512) this machine
// runs. Each vectorised kernel is compiled once per ISA (render/cpu/CMakeLists.txt) and picks its
// build through this one test, so all kernels agree on the choice.
#pragma once

namespace streetsim::cpu {

enum class SimdIsa { kAvx2, kAvx512, kGeneric };

inline SimdIsa DetectSimdIsa() {
#if defined(__x86_64__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
      __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl")) {
    return SimdIsa::kAvx512;
  }
  return SimdIsa::kAvx2;
#else
  return SimdIsa::kGeneric;
#endif
}

// Picks the AVX-512 build when the machine has it, else the AVX2 (or generic) build.
template <typename Fn>
Fn PickSimd(Fn avx2_or_generic, Fn avx512) {
  return DetectSimdIsa() == SimdIsa::kAvx512 ? avx512 : avx2_or_generic;
}

}  // namespace streetsim::cpu
