// Large arrays sampled at random texels (the planes, their gradients) on transparent huge pages:
// with 4 KiB pages nearly every tap of a 32 MiB plane misses the TLB, and the page walks cost
// more than the cache misses. Debian's default THP mode is "madvise", so ask for it.
#pragma once

#include <cstddef>
#include <vector>

namespace streetsim::field {

// Advises huge pages for the whole 2 MiB pages inside [p, p + bytes). Harmless where unsupported.
void AdviseHugePages(void* p, size_t bytes);

// Replaces *v by a copy whose storage was advised before its first touch.
template <typename T>
void MoveToHugePages(std::vector<T>* v) {
  std::vector<T> h;
  h.reserve(v->size());
  AdviseHugePages(h.data(), h.capacity() * sizeof(T));
  h.assign(v->begin(), v->end());
  v->swap(h);
}

// *v = n copies of value, on advised storage.
template <typename T>
void AssignOnHugePages(std::vector<T>* v, size_t n, T value) {
  std::vector<T> h;
  h.reserve(n);
  AdviseHugePages(h.data(), h.capacity() * sizeof(T));
  h.assign(n, value);
  v->swap(h);
}

}  // namespace streetsim::field
