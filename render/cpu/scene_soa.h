// The cpu backend's copy of a scene: one contiguous array per scalar parameter, so that the
// projection loop reads 16 Gaussians' x (or log-scale, or SH coefficient k of channel c) with one
// vector load instead of gathering through the interleaved store layout.
#pragma once

#include <cstddef>
#include <new>
#include <vector>

#include "absl/status/status.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::cpu {

// Storage whose first element starts a 64-byte cache line.
template <typename T>
struct CacheLineAllocator {
  using value_type = T;
  CacheLineAllocator() = default;
  template <typename U>
  CacheLineAllocator(const CacheLineAllocator<U>&) {}
  T* allocate(size_t count) { return static_cast<T*>(::operator new(count * sizeof(T), std::align_val_t{64})); }
  void deallocate(T* ptr, size_t) { ::operator delete(ptr, std::align_val_t{64}); }
  template <typename U>
  bool operator==(const CacheLineAllocator<U>&) const { return true; }
};

struct SceneSoa {
  size_t n = 0;
  int sh_degree = 0;
  std::vector<float> mx, my, mz;
  std::vector<float> ls0, ls1, ls2;
  std::vector<float> qw, qx, qy, qz;
  std::vector<float> opacity_logit;
  // Plane (k*3 + c) holds SH coefficient k of channel c for all Gaussians:
  // sh[(k*3+c)*sh_plane + i]. Planes are n rounded up to 16 floats apart, so that every plane and
  // every run of 16 Gaussians starting at a multiple of 16 is one whole cache line: serving writes
  // such runs with streaming stores (AssignRows).
  size_t sh_plane = 0;
  std::vector<float, CacheLineAllocator<float>> sh;

  static SceneSoa FromStore(const GaussianStore& store);
  // Training: overwrites this copy from a parameter view in place (vectors keep their capacity),
  // in parallel, checking only what rendering needs: finite values and non-zero rotations.
  // On error the contents are unspecified.
  absl::Status Assign(ThreadPool& pool, const GaussianParamsView& p);
  // Serving: overwrites only `change`'s rows and values (the view must have this copy's size and SH
  // degree), checking them as Assign does. On error the changed rows are unspecified.
  absl::Status AssignRows(ThreadPool& pool, const GaussianParamsView& p, const ParamsChange& change);
};

}  // namespace streetsim::cpu
