#include "server/digest.h"

#include <cstdio>
#include <cstring>

namespace streetsim::server {
namespace {

constexpr uint64_t kPrime = 0x100000001b3ull;

uint64_t Step(uint64_t h, uint64_t w) {
  h = (h ^ w) * kPrime;
  return h ^ (h >> 29);
}

}  // namespace

void ContentDigest::Word(uint64_t w) { h_ = Step(h_, w); }

void ContentDigest::Update(std::string_view bytes) {
  length_ += bytes.size();
  size_t i = 0;
  while (pending_bytes_ != 0 && i < bytes.size()) {  // finish a word begun by an earlier call
    pending_ |= uint64_t{static_cast<unsigned char>(bytes[i++])} << (8 * pending_bytes_);
    if (++pending_bytes_ == 8) {
      Word(pending_);
      pending_ = 0;
      pending_bytes_ = 0;
    }
  }
  uint64_t h = h_;
  for (; i + 8 <= bytes.size(); i += 8) {
    uint64_t w;
    std::memcpy(&w, bytes.data() + i, 8);  // little-endian on every supported host
    h = Step(h, w);
  }
  h_ = h;
  for (; i < bytes.size(); ++i) {
    pending_ |= uint64_t{static_cast<unsigned char>(bytes[i])} << (8 * pending_bytes_++);
  }
}

std::string ContentDigest::Hex() const {
  uint64_t h = h_;
  if (pending_bytes_ != 0) h = Step(h, pending_);
  h = Step(h, length_);
  char buf[32];
  std::snprintf(buf, sizeof(buf), "fnv1a64w:%016llx", static_cast<unsigned long long>(h));
  return buf;
}

std::string DigestOf(std::string_view bytes) {
  ContentDigest d;
  d.Update(bytes);
  return d.Hex();
}

}  // namespace streetsim::server
