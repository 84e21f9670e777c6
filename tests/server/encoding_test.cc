// Payload encoding (server/image_encoding.h) and content digests (server/digest.h): the RGB bytes
// are lround(clamp(v) * 255) with every non-finite value black, and the digest is the function
// docs/server.md writes down, however the bytes arrive.
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "server/digest.h"
#include "server/image_encoding.h"

namespace streetsim::testing {
namespace {

using server::ContentDigest;
using server::DigestOf;

// The digest written out step by step from its definition (docs/server.md "Digests").
std::string ReferenceDigest(const std::string& bytes) {
  auto step = [](uint64_t h, uint64_t w) {
    h = (h ^ w) * 0x100000001b3ull;
    return h ^ (h >> 29);
  };
  uint64_t h = 0xcbf29ce484222325ull;
  for (size_t i = 0; i < bytes.size(); i += 8) {
    uint64_t w = 0;
    for (size_t k = 0; k < 8 && i + k < bytes.size(); ++k) {
      w |= uint64_t{static_cast<unsigned char>(bytes[i + k])} << (8 * k);
    }
    h = step(h, w);
  }
  h = step(h, bytes.size());
  char buf[32];
  std::snprintf(buf, sizeof(buf), "fnv1a64w:%016llx", static_cast<unsigned long long>(h));
  return buf;
}

TEST(ContentDigest, IsTheDocumentedFunctionHoweverTheBytesAreSplit) {
  std::mt19937 rng(3);
  for (size_t len : {0u, 1u, 7u, 8u, 9u, 63u, 1000u}) {
    std::string bytes(len, '\0');
    for (char& c : bytes) c = static_cast<char>(rng());
    const std::string want = ReferenceDigest(bytes);
    EXPECT_EQ(DigestOf(bytes), want) << len;
    for (size_t cut1 = 0; cut1 <= len; cut1 += 3) {
      const size_t cut2 = (cut1 + len) / 2;
      ContentDigest d;
      d.Update(std::string_view(bytes).substr(0, cut1));
      d.Update(std::string_view(bytes).substr(cut1, cut2 - cut1));
      d.Update(std::string_view(bytes).substr(cut2));
      ASSERT_EQ(d.Hex(), want) << len << " cut at " << cut1 << ", " << cut2;
    }
  }
}

TEST(ContentDigest, TellsApartWhatAFrameDigestMustTellApart) {
  const std::string a(4096, '\x10');
  std::string b = a;
  b[4000] = '\x11';  // one level in one pixel, late in the frame
  std::string c = a;
  c[7] = '\x90';  // a high bit in the first word
  EXPECT_NE(DigestOf(a), DigestOf(b));
  EXPECT_NE(DigestOf(a), DigestOf(c));
  EXPECT_NE(DigestOf(std::string(9, '\0')), DigestOf(std::string(10, '\0')));  // zero padding vs zeros
  EXPECT_NE(DigestOf(""), DigestOf(std::string(1, '\0')));
}

TEST(EncodeRgb, RoundsLikeLroundAndBlacksOutNonFiniteValues) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  std::vector<float> rgb = {0.0f, 1.0f, -0.5f, 2.0f, kInf, -kInf, std::nanf(""), 0.5f / 255.0f,
                            std::nextafter(0.5f / 255.0f, 0.0f), 254.5f / 255.0f, 0.1234f, 0.9999f};
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-0.1f, 1.1f);
  while (rgb.size() < 3 * 1000) rgb.push_back(u(rng));
  // Values whose product with 255 falls just below and on every half level.
  for (int k = 0; k < 255 && rgb.size() < 3 * 1400; ++k) {
    const float half = (static_cast<float>(k) + 0.5f) / 255.0f;
    rgb.push_back(half);
    rgb.push_back(std::nextafter(half, 0.0f));
    rgb.push_back(std::nextafter(half, 1.0f));
  }
  while (rgb.size() % 3 != 0) rgb.push_back(0.0f);
  const int width = static_cast<int>(rgb.size() / 3);
  v1::Image image;
  ASSERT_TRUE(server::EncodeRgb(width, 1, rgb, v1::IMAGE_ENCODING_RAW, 0, &image).ok());
  ASSERT_EQ(image.data().size(), rgb.size());
  for (size_t i = 0; i < rgb.size(); ++i) {
    const float v = std::isfinite(rgb[i]) ? std::fmin(std::fmax(rgb[i], 0.0f), 1.0f) : 0.0f;
    ASSERT_EQ(static_cast<uint8_t>(image.data()[i]), static_cast<uint8_t>(std::lround(v * 255.0f)))
        << "value " << i << " = " << rgb[i];
  }
  EXPECT_EQ(image.digest(), DigestOf(image.data()));
}

}  // namespace
}  // namespace streetsim::testing
