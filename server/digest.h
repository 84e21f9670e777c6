// Content digests of response payloads (not cryptographic; they identify frames for determinism
// checks and caching, they do not authenticate them). Printed "fnv1a64w:<16 hex>".
//
// The function, so that a client can recompute it (docs/server.md "Digests"): FNV-1a taken over
// 64-bit little-endian words instead of bytes, each step h = ((h ^ word) * 0x100000001b3), then
// h ^= h >> 29 (the fold carries high bits down, which a word-wide multiply alone never does); a
// last partial word is zero-padded, and the byte length is folded in as one more word. One
// multiply per 8 bytes instead of per byte (byte-wise FNV-1a was 6.5 % of a 500k step's cpu
// samples, on one thread: docs/benchmarks.md). Each step is a bijection of h, so two inputs of
// equal length that differ in a single word always differ in digest.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

namespace streetsim::server {

class ContentDigest {
 public:
  void Update(std::string_view bytes);
  std::string Hex() const;  // "fnv1a64w:%016x" of everything updated so far

 private:
  void Word(uint64_t w);

  uint64_t h_ = 0xcbf29ce484222325ull;
  uint64_t length_ = 0;
  uint64_t pending_ = 0;  // the bytes of a word not yet full, little-endian
  int pending_bytes_ = 0;
};

std::string DigestOf(std::string_view bytes);

}  // namespace streetsim::server
