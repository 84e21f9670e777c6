#include "server/digest.h"

#include <cstdio>

namespace streetsim::server {

void Fnv1a64::Update(std::string_view bytes) {
  uint64_t h = h_;
  for (unsigned char c : bytes) {
    h ^= c;
    h *= 0x100000001b3ull;
  }
  h_ = h;
}

std::string Fnv1a64::Hex() const {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "fnv1a64:%016llx", static_cast<unsigned long long>(h_));
  return buf;
}

std::string DigestOf(std::string_view bytes) {
  Fnv1a64 h;
  h.Update(bytes);
  return h.Hex();
}

}  // namespace streetsim::server
