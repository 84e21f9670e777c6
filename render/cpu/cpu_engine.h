// The cpu backend: multithreaded, compiler-vectorised C++.
#pragma once

#include <memory>

#include "render/engine.h"

namespace streetsim {

enum class CpuPrecision {
  kFloatSimd,    // production: vectorised float blend (AVX2 / AVX-512 chosen at run time)
  kFloatScalar,  // same arithmetic one pixel at a time, std::exp (reference for kFloatSimd)
  kDouble,       // double throughout projection and blend (reference for gradient checks)
};

struct CpuEngineOptions {
  int num_threads = 0;  // <= 0: STREETSIM_THREADS or all hardware threads
  CpuPrecision precision = CpuPrecision::kFloatSimd;
};

std::unique_ptr<Engine> CreateCpuEngine(const CpuEngineOptions& options = {});

}  // namespace streetsim
