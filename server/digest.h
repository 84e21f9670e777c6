// Content digests of response payloads: 64-bit FNV-1a (not cryptographic; it identifies frames
// for determinism checks and caching, it does not authenticate them). Printed "fnv1a64:<16 hex>".
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

namespace streetsim::server {

class Fnv1a64 {
 public:
  void Update(std::string_view bytes);
  uint64_t value() const { return h_; }
  std::string Hex() const;  // "fnv1a64:%016x"

 private:
  uint64_t h_ = 0xcbf29ce484222325ull;
};

std::string DigestOf(std::string_view bytes);

}  // namespace streetsim::server
