#include "scene/gaussians/ply_io.h"

#include <dirent.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "gtest/gtest.h"

namespace streetsim {
namespace {

std::string DataPath(const std::string& name) {
  return absl::StrCat(STREETSIM_DATA_DIR, "/ply/", name);
}

std::string ReadFileBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

void WriteFileBytes(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

std::string TempPath(const std::string& name) {
  return absl::StrCat(testing::TempDir(), "ply_io_test_", ::getpid(), "_", name);
}

// The canonical INRIA property list, spelled out here rather than taken from the code under test.
std::vector<std::string> InriaProperties(int degree, bool normals) {
  std::vector<std::string> p = {"x", "y", "z"};
  if (normals) p.insert(p.end(), {"nx", "ny", "nz"});
  p.insert(p.end(), {"f_dc_0", "f_dc_1", "f_dc_2"});
  const int rest = 3 * ((degree + 1) * (degree + 1) - 1);
  for (int r = 0; r < rest; ++r) p.push_back(absl::StrCat("f_rest_", r));
  p.insert(p.end(),
           {"opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"});
  return p;
}

// Independent statement of the layout: the value of property `name` for Gaussian i.
float StoreValue(const GaussianStore& s, size_t i, const std::string& name) {
  const size_t k = static_cast<size_t>(s.sh_coeffs());
  const auto idx = [&](const char* prefix) { return std::stoul(name.substr(std::strlen(prefix))); };
  if (name == "x" || name == "y" || name == "z") return s.means[i * 3 + (name[0] - 'x')];
  if (name == "nx" || name == "ny" || name == "nz") return s.normals[i * 3 + (name[1] - 'x')];
  if (name == "opacity") return s.opacity_logits[i];
  if (absl::StartsWith(name, "f_dc_")) return s.sh[(i * k + 0) * 3 + idx("f_dc_")];
  if (absl::StartsWith(name, "f_rest_")) {
    const size_t r = idx("f_rest_");
    const size_t c = r / (k - 1), coeff = r % (k - 1) + 1;
    return s.sh[(i * k + coeff) * 3 + c];
  }
  if (absl::StartsWith(name, "scale_")) return s.log_scales[i * 3 + idx("scale_")];
  if (absl::StartsWith(name, "rot_")) return s.rotations[i * 4 + idx("rot_")];
  ADD_FAILURE() << "unknown property " << name;
  return 0;
}

// Builds a PLY with the given column order; `type` and `extra_header` allow header variations.
std::string BuildPly(const GaussianStore& s, const std::vector<std::string>& props,
                     const std::string& type = "float", const std::string& newline = "\n") {
  std::string out =
      absl::StrCat("ply", newline, "format binary_little_endian 1.0", newline,
                   "comment built by ply_io_test", newline, "element vertex ", s.size(), newline);
  for (const std::string& p : props) absl::StrAppend(&out, "property ", type, " ", p, newline);
  absl::StrAppend(&out, "end_header", newline);
  for (size_t i = 0; i < s.size(); ++i) {
    for (const std::string& p : props) {
      const float v = StoreValue(s, i, p);
      out.append(reinterpret_cast<const char*>(&v), sizeof(v));
    }
  }
  return out;
}

GaussianStore RandomStore(size_t n, int degree, bool normals, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> dist(0.f, 2.f);
  GaussianStore s;
  s.sh_degree = degree;
  if (normals) s.normals.resize(1);  // Resize keeps normals only when non-empty
  s.Resize(n);
  for (auto* v : {&s.means, &s.log_scales, &s.rotations, &s.opacity_logits, &s.sh, &s.normals}) {
    for (float& x : *v) x = dist(rng);
  }
  for (size_t i = 0; i < n; ++i) s.rotations[i * 4] = 1.f + std::abs(s.rotations[i * 4]);
  return s;
}

void ExpectStoresEqual(const GaussianStore& a, const GaussianStore& b) {
  EXPECT_EQ(a.sh_degree, b.sh_degree);
  EXPECT_EQ(a.means, b.means);
  EXPECT_EQ(a.log_scales, b.log_scales);
  EXPECT_EQ(a.rotations, b.rotations);
  EXPECT_EQ(a.opacity_logits, b.opacity_logits);
  EXPECT_EQ(a.sh, b.sh);
  EXPECT_EQ(a.normals, b.normals);
}

// A small degree-1 file with normals: 3 Gaussians, 26 floats each.
std::string SmallPly() { return SerializeGaussianPly(RandomStore(3, 1, true, 7)); }

size_t HeaderSize(const std::string& bytes) {
  return bytes.find("end_header\n") + std::strlen("end_header\n");
}

void SetFloat(std::string* bytes, size_t offset, float v) {
  std::memcpy(bytes->data() + offset, &v, sizeof(v));
}

float GetFloat(const std::string& bytes, size_t offset) {
  float v;
  std::memcpy(&v, bytes.data() + offset, sizeof(v));
  return v;
}

std::string Replace(const std::string& s, const std::string& from, const std::string& to) {
  EXPECT_TRUE(absl::StrContains(s, from)) << from;
  return absl::StrReplaceAll(s, {{from, to}});
}

void ExpectInvalid(const std::string& bytes, const std::string& message_part,
                   const PlyReadOptions& options = {}) {
  const absl::StatusOr<GaussianStore> r = ParseGaussianPly(bytes, options);
  ASSERT_FALSE(r.ok()) << "expected an error containing: " << message_part;
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << r.status();
  EXPECT_TRUE(absl::StrContains(r.status().message(), message_part)) << r.status().message();
}

// Checks every float of selected records against the file read independently by offset.
void SpotCheck(const std::string& file, const GaussianStore& s, int degree, bool normals) {
  const std::vector<std::string> props = InriaProperties(degree, normals);
  const size_t header = HeaderSize(file);
  const size_t stride = props.size() * 4;
  for (size_t i : {size_t{0}, size_t{1}, s.size() / 2, s.size() - 1}) {
    for (size_t j = 0; j < props.size(); ++j) {
      EXPECT_EQ(StoreValue(s, i, props[j]), GetFloat(file, header + i * stride + j * 4))
          << "Gaussian " << i << " " << props[j];
    }
  }
}

TEST(PlyIoTest, LoadsInriaSh3File) {
  const std::string path = DataPath("inria_sh3_9080.ply");
  absl::StatusOr<GaussianStore> s = ReadGaussianPly(path);
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->size(), 9080u);
  EXPECT_EQ(s->sh_degree, 3);
  EXPECT_EQ(s->normals.size(), 9080u * 3);
  EXPECT_EQ(s->sh.size(), 9080u * 16 * 3);
  EXPECT_TRUE(s->Validate().ok());
  EXPECT_FLOAT_EQ(s->means[0], 7.31924295425415f);
  EXPECT_FLOAT_EQ(s->means[1], -16.327651977539062f);
  EXPECT_FLOAT_EQ(s->opacity_logits[0], -4.595119953155518f);
  EXPECT_FLOAT_EQ(s->rotations[0], 0.9921094179153442f);
  const std::string file = ReadFileBytes(path);
  SpotCheck(file, *s, 3, true);
  // Find a Gaussian with non-zero higher-order SH so the channel-major mapping is really exercised.
  bool found = false;
  for (size_t i = 0; i < s->size() && !found; ++i) {
    const size_t base = HeaderSize(file) + i * 62 * 4;
    if (GetFloat(file, base + (9 + 15) * 4) == 0.f) continue;  // f_rest_15: green, k = 1
    found = true;
    EXPECT_EQ(s->sh[(i * 16 + 1) * 3 + 1], GetFloat(file, base + (9 + 15) * 4));
    EXPECT_EQ(s->sh[(i * 16 + 15) * 3 + 2], GetFloat(file, base + (9 + 44) * 4));  // blue, k = 15
    EXPECT_EQ(s->sh[(i * 16 + 2) * 3 + 0], GetFloat(file, base + (9 + 1) * 4));    // red, k = 2
  }
  EXPECT_TRUE(found) << "no Gaussian with non-zero f_rest_15";
}

TEST(PlyIoTest, LoadsMipSh0File) {
  const std::string path = DataPath("mip_sh0_45624.ply");
  absl::StatusOr<GaussianStore> s = ReadGaussianPly(path);
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->size(), 45624u);
  EXPECT_EQ(s->sh_degree, 0);
  EXPECT_TRUE(s->normals.empty());
  EXPECT_EQ(s->sh.size(), 45624u * 3);
  EXPECT_FLOAT_EQ(s->means[2], 0.040593795478343964f);
  EXPECT_FLOAT_EQ(s->sh[1], 1.3836876153945923f);
  EXPECT_FLOAT_EQ(s->opacity_logits[0], 6.068385601043701f);
  EXPECT_FLOAT_EQ(s->log_scales[2], -5.855655193328857f);
  EXPECT_FLOAT_EQ(s->rotations[3], 0.25336384773254395f);
  SpotCheck(ReadFileBytes(path), *s, 0, false);
}

TEST(PlyIoTest, SharedFilesRoundTripByteIdentical) {
  for (const char* name : {"inria_sh3_9080.ply", "mip_sh0_45624.ply"}) {
    SCOPED_TRACE(name);
    const std::string original = ReadFileBytes(DataPath(name));
    absl::StatusOr<GaussianStore> s = ParseGaussianPly(original);
    ASSERT_TRUE(s.ok()) << s.status();
    EXPECT_TRUE(SerializeGaussianPly(*s) == original);
  }
}

TEST(PlyIoTest, RandomStoresRoundTrip) {
  for (int degree = 0; degree <= 3; ++degree) {
    for (bool normals : {false, true}) {
      SCOPED_TRACE(absl::StrCat("degree ", degree, " normals ", normals));
      const GaussianStore s = RandomStore(37, degree, normals, 100 + degree * 2 + normals);
      const std::string bytes = SerializeGaussianPly(s);
      EXPECT_TRUE(
          absl::StartsWith(bytes, "ply\nformat binary_little_endian 1.0\nelement vertex 37\n"));
      EXPECT_EQ(absl::StrContains(bytes, "property float nx\n"), normals);
      EXPECT_EQ(absl::StrContains(bytes, "f_rest_0\n"), degree > 0);
      // The serializer must agree with the independently written layout.
      EXPECT_TRUE(bytes == Replace(BuildPly(s, InriaProperties(degree, normals)),
                                   "comment built by ply_io_test\n", ""));
      absl::StatusOr<GaussianStore> back = ParseGaussianPly(bytes);
      ASSERT_TRUE(back.ok()) << back.status();
      ExpectStoresEqual(s, *back);
      EXPECT_TRUE(SerializeGaussianPly(*back) == bytes);
    }
  }
}

TEST(PlyIoTest, EmptyStoreRoundTrips) {
  GaussianStore s;
  s.sh_degree = 2;
  absl::StatusOr<GaussianStore> back = ParseGaussianPly(SerializeGaussianPly(s));
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->size(), 0u);
  EXPECT_EQ(back->sh_degree, 2);
}

TEST(PlyIoTest, AcceptsAnyPropertyOrderFloat32AndCrlf) {
  const GaussianStore s = RandomStore(11, 2, true, 5);
  std::vector<std::string> props = InriaProperties(2, true);
  std::mt19937 rng(3);
  for (int trial = 0; trial < 5; ++trial) {
    std::shuffle(props.begin(), props.end(), rng);
    for (const char* type : {"float", "float32"}) {
      for (const char* nl : {"\n", "\r\n"}) {
        absl::StatusOr<GaussianStore> back = ParseGaussianPly(BuildPly(s, props, type, nl));
        ASSERT_TRUE(back.ok()) << back.status();
        ExpectStoresEqual(s, *back);
      }
    }
  }
}

TEST(PlyIoTest, AcceptsCommentsObjInfoAndEmptyOtherElements) {
  const std::string good = SmallPly();
  std::string bytes = Replace(good, "format binary_little_endian 1.0\n",
                              "comment a\nformat binary_little_endian 1.0\nobj_info b c\n");
  bytes =
      Replace(bytes, "end_header\n",
              "element face 0\nproperty list uchar int vertex_indices\ncomment x\nend_header\n");
  absl::StatusOr<GaussianStore> a = ParseGaussianPly(bytes);
  absl::StatusOr<GaussianStore> b = ParseGaussianPly(good);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  ExpectStoresEqual(*a, *b);
}

TEST(PlyIoTest, TrailingNewlineToleratedGarbageRejected) {
  const std::string good = SmallPly();
  EXPECT_TRUE(ParseGaussianPly(good + "\n").ok());
  EXPECT_TRUE(ParseGaussianPly(good + "\r\n").ok());
  ExpectInvalid(good + "\n\n\n", "unexpected bytes");
  ExpectInvalid(good + "x", "unexpected bytes");
  ExpectInvalid(good + std::string(4, '\0'), "unexpected bytes");
}

TEST(PlyIoTest, RejectsMalformedHeaders) {
  const std::string good = SmallPly();  // degree 1 (f_rest_0..8), with normals
  const std::string fmt = "format binary_little_endian 1.0";
  ExpectInvalid("", "without an end_header");
  ExpectInvalid("ply\n", "without an end_header");
  ExpectInvalid(Replace(good, "ply\n", "plx\n"), "not a PLY file");
  ExpectInvalid(Replace(good, fmt, "format ascii 1.0"), "unsupported format 'ascii'");
  ExpectInvalid(Replace(good, fmt, "format binary_big_endian 1.0"), "binary_big_endian");
  ExpectInvalid(Replace(good, fmt, "format binary_little_endian 2.0"), "version");
  ExpectInvalid(Replace(good, fmt + "\n", ""), "element before the format line");
  ExpectInvalid(Replace(good, fmt + "\n", fmt + "\n" + fmt + "\n"), "duplicate format");
  ExpectInvalid(Replace(good, "property float opacity", "property double opacity"),
                "has type 'double'");
  ExpectInvalid(Replace(good, "property float opacity", "property uchar opacity"), "only float");
  ExpectInvalid(Replace(good, "property float opacity", "property float alpha"),
                "unexpected property 'alpha'");
  ExpectInvalid(Replace(good, "end_header\n", "property float red\nend_header\n"),
                "unexpected property 'red'");
  ExpectInvalid(Replace(good, "property float x", "property list uchar float x"), "list");
  ExpectInvalid(Replace(good, "property float opacity\n", ""),
                "missing required properties: opacity");
  ExpectInvalid(Replace(good, "property float rot_3\n", ""), "rot_3");
  ExpectInvalid(Replace(good, "property float nz\n", ""), "normals");
  ExpectInvalid(Replace(good, "property float f_rest_8\n", ""), "8 f_rest properties");
  ExpectInvalid(Replace(good, "property float f_rest_8\n", "property float f_rest_9\n"), "gap");
  ExpectInvalid(Replace(good, "property float f_rest_8\n", "property float f_rest_7\n"),
                "duplicate property 'f_rest_7'");
  ExpectInvalid(Replace(good, "property float f_rest_8\n", "property float f_rest_45\n"),
                "unexpected property 'f_rest_45'");
  ExpectInvalid(Replace(good, "property float f_rest_1\n", "property float f_rest_01\n"),
                "unexpected property 'f_rest_01'");
  ExpectInvalid(Replace(good, "property float x\n", "property float x\nproperty float x\n"),
                "duplicate property 'x'");
  ExpectInvalid(
      Replace(good, "end_header\n", "element face 2\nproperty list uchar int i\nend_header\n"),
      "element 'face' has 2 entries");
  ExpectInvalid(Replace(good, "element vertex 3\n", "element vertex 3\nelement vertex 3\n"),
                "duplicate vertex element");
  ExpectInvalid(Replace(good, "element vertex 3\n", "element face 0\nproperty float y\n"),
                "no vertex element");
  ExpectInvalid(Replace(good, "element vertex 3\n", ""), "property before any element");
  ExpectInvalid(Replace(good, "element vertex 3", "element vertex -3"), "malformed element");
  ExpectInvalid(Replace(good, "element vertex 3", "element vertex +3"), "malformed element");
  ExpectInvalid(Replace(good, "element vertex 3", "element vertex 3x"), "malformed element");
  ExpectInvalid(Replace(good, "element vertex 3", "element vertex 99999999999999999999999"),
                "malformed element");
  ExpectInvalid(Replace(good, "end_header\n", "bogus line\nend_header\n"),
                "unknown header keyword");
  ExpectInvalid(Replace(good, "end_header\n", "end_header now\n"), "end_header");
  ExpectInvalid(Replace(good, "end_header\n", "end_headr\n"), "unknown header keyword");
}

TEST(PlyIoTest, HeaderMustEndWithin64KiB) {
  const std::string good = SmallPly();
  const std::string comment = "comment " + std::string(100, 'c') + "\n";
  std::string padded_small = good, padded_big = good;
  std::string small_pad, big_pad;
  for (int i = 0; i < 500; ++i) small_pad += comment;  // ~54 KiB
  for (int i = 0; i < 700; ++i) big_pad += comment;    // ~76 KiB
  padded_small.insert(4, small_pad);
  padded_big.insert(4, big_pad);
  EXPECT_TRUE(ParseGaussianPly(padded_small).ok());
  ExpectInvalid(padded_big, "no end_header within the first 65536 bytes");
  // No newline at all in a large file: must stop searching at the limit.
  ExpectInvalid("ply\n" + std::string(200000, 'a'), "no end_header within");
}

TEST(PlyIoTest, RejectsTooManyGaussians) {
  PlyReadOptions opt;
  opt.max_gaussians = 2;
  ExpectInvalid(SmallPly(), "declares 3 Gaussians, more than the limit of 2", opt);
  opt.max_gaussians = 3;
  EXPECT_TRUE(ParseGaussianPly(SmallPly(), opt).ok());
}

TEST(PlyIoTest, AbsurdCountFailsBeforeAllocating) {
  const std::string bad = Replace(SmallPly(), "element vertex 3", "element vertex 4000000000");
  ExpectInvalid(bad, "more than the limit");
  // Even with no limit, the count is checked against the bytes present before allocating
  // (a 4e9-Gaussian allocation would take ~350 GB and abort the test under ASan).
  PlyReadOptions unlimited;
  unlimited.max_gaussians = std::numeric_limits<size_t>::max();
  ExpectInvalid(bad, "truncated", unlimited);
  ExpectInvalid(Replace(SmallPly(), "element vertex 3", "element vertex 18446744073709551615"),
                "truncated", unlimited);
}

TEST(PlyIoTest, RejectsTruncatedBody) {
  const std::string good = SmallPly();
  ExpectInvalid(good.substr(0, good.size() - 1), "truncated");
  ExpectInvalid(good.substr(0, HeaderSize(good)), "truncated");
}

// Byte offset of `prop` of Gaussian i in SmallPly().
size_t SmallPlyOffset(const std::string& bytes, size_t i, const std::string& prop) {
  const std::vector<std::string> props = InriaProperties(1, true);
  const size_t j = std::find(props.begin(), props.end(), prop) - props.begin();
  EXPECT_LT(j, props.size()) << prop;
  return HeaderSize(bytes) + (i * props.size() + j) * sizeof(float);
}

TEST(PlyIoTest, RejectsNonFiniteValuesNamingGaussianAndProperty) {
  const std::string good = SmallPly();
  std::string bad = good;
  SetFloat(&bad, SmallPlyOffset(bad, 2, "opacity"), std::numeric_limits<float>::quiet_NaN());
  ExpectInvalid(bad, "Gaussian 2 property 'opacity' is not finite");
  bad = good;
  SetFloat(&bad, SmallPlyOffset(bad, 1, "f_rest_3"), -std::numeric_limits<float>::infinity());
  ExpectInvalid(bad, "Gaussian 1 property 'f_rest_3' is not finite (-inf)");
  bad = good;
  SetFloat(&bad, SmallPlyOffset(bad, 0, "nx"), std::numeric_limits<float>::infinity());
  ExpectInvalid(bad, "Gaussian 0 property 'nx' is not finite (inf)");
}

TEST(PlyIoTest, RejectsZeroRotation) {
  std::string bad = SmallPly();
  for (int q = 0; q < 4; ++q) SetFloat(&bad, SmallPlyOffset(bad, 1, absl::StrCat("rot_", q)), 0.f);
  ExpectInvalid(bad, "rotation 1 is zero");
}

TEST(PlyIoTest, EveryTruncatedPrefixIsAnError) {
  const std::string good = SmallPly();
  ASSERT_TRUE(ParseGaussianPly(good).ok());
  for (size_t len = 0; len < good.size(); ++len) {
    const std::string prefix = good.substr(0, len);  // own buffer so ASan sees over-reads
    const absl::StatusOr<GaussianStore> r = ParseGaussianPly(prefix);
    ASSERT_FALSE(r.ok()) << "prefix of " << len << " bytes parsed";
    ASSERT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  }
}

TEST(PlyIoTest, ByteFlipFuzzNeverCrashes) {
  const std::string good = SmallPly();
  const size_t header = HeaderSize(good);
  std::mt19937 rng(12345);
  int ok = 0, errors = 0;
  for (int iter = 0; iter < 4000; ++iter) {
    std::string bytes = good;
    const int edits = 1 + static_cast<int>(rng() % 4);
    for (int e = 0; e < edits; ++e) {
      // Mostly target the header, where the parsing logic is.
      const size_t limit = (rng() % 4 == 0) ? bytes.size() : std::min(header, bytes.size());
      if (limit == 0) break;
      const size_t pos = rng() % limit;
      switch (rng() % 4) {
        case 0:
          bytes[pos] = static_cast<char>(bytes[pos] ^ (1u << (rng() % 8)));
          break;
        case 1:
          bytes[pos] = static_cast<char>(rng());
          break;
        case 2:
          bytes.erase(pos, 1 + rng() % 8);
          break;
        default:
          bytes.insert(pos, 1, "\n\r 0f_9x"[rng() % 8]);
          break;
      }
    }
    const absl::StatusOr<GaussianStore> r = ParseGaussianPly(std::string(bytes));
    if (r.ok()) {
      ++ok;
      EXPECT_TRUE(r->Validate().ok());
    } else {
      ++errors;
      EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
    }
  }
  EXPECT_GT(errors, 0);
  RecordProperty("fuzz_ok", ok);
}

TEST(PlyIoTest, ReadErrorsStartWithPath) {
  const std::string missing = TempPath("does_not_exist.ply");
  absl::StatusOr<GaussianStore> r = ReadGaussianPly(missing);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_TRUE(absl::StartsWith(r.status().message(), missing)) << r.status().message();

  r = ReadGaussianPly(testing::TempDir());
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StartsWith(r.status().message(), testing::TempDir())) << r.status().message();

  const std::string bad_path = TempPath("bad.ply");
  WriteFileBytes(bad_path, Replace(SmallPly(), "format binary_little_endian", "format ascii"));
  r = ReadGaussianPly(bad_path);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StartsWith(r.status().message(), bad_path + ": ")) << r.status().message();
  EXPECT_TRUE(absl::StrContains(r.status().message(), "ascii")) << r.status().message();

  const std::string empty_path = TempPath("empty.ply");
  WriteFileBytes(empty_path, "");
  r = ReadGaussianPly(empty_path);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StartsWith(r.status().message(), empty_path)) << r.status().message();

  // A FIFO must be refused without blocking on open.
  const std::string fifo_path = TempPath("fifo.ply");
  ASSERT_EQ(::mkfifo(fifo_path.c_str(), 0600), 0);
  r = ReadGaussianPly(fifo_path);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(r.status().message(), "not a regular file"))
      << r.status().message();
  ::unlink(fifo_path.c_str());

  PlyReadOptions opt;
  opt.max_gaussians = 1;  // the shared file is far larger than any 1-Gaussian PLY
  r = ReadGaussianPly(DataPath("mip_sh0_45624.ply"), opt);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  std::remove(bad_path.c_str());
  std::remove(empty_path.c_str());
}

bool TempFilesLeft(const std::string& dir, const std::string& stem) {
  DIR* d = opendir(dir.c_str());
  if (d == nullptr) return false;
  bool found = false;
  while (dirent* e = readdir(d)) {
    if (absl::StartsWith(e->d_name, stem) && absl::StrContains(e->d_name, ".tmp.")) found = true;
  }
  closedir(d);
  return found;
}

TEST(PlyIoTest, WriteReadRoundTripAndOverwrite) {
  const std::string path = TempPath("roundtrip.ply");
  const std::string stem = path.substr(path.find_last_of('/') + 1);
  const std::string dir = path.substr(0, path.find_last_of('/'));
  for (int degree = 0; degree <= 3; ++degree) {
    const GaussianStore s = RandomStore(20 + degree, degree, degree % 2 == 1, 40 + degree);
    ASSERT_TRUE(WriteGaussianPly(s, path).ok());  // overwrites the previous iteration's file
    EXPECT_FALSE(TempFilesLeft(dir, stem));
    absl::StatusOr<GaussianStore> back = ReadGaussianPly(path);
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectStoresEqual(s, *back);
    EXPECT_TRUE(ReadFileBytes(path) == SerializeGaussianPly(s));
  }
  std::remove(path.c_str());
}

TEST(PlyIoTest, SharedFileWriteReadWriteIdentical) {
  absl::StatusOr<GaussianStore> s = ReadGaussianPly(DataPath("inria_sh3_9080.ply"));
  ASSERT_TRUE(s.ok()) << s.status();
  const std::string path = TempPath("inria_copy.ply");
  ASSERT_TRUE(WriteGaussianPly(*s, path).ok());
  EXPECT_TRUE(ReadFileBytes(path) == ReadFileBytes(DataPath("inria_sh3_9080.ply")));
  absl::StatusOr<GaussianStore> back = ReadGaussianPly(path);
  ASSERT_TRUE(back.ok()) << back.status();
  ExpectStoresEqual(*s, *back);
  std::remove(path.c_str());
}

TEST(PlyIoTest, WriteFailuresLeaveNothingBehind) {
  // Invalid store: refused before touching the file system.
  GaussianStore bad = RandomStore(4, 1, false, 9);
  bad.opacity_logits[2] = std::numeric_limits<float>::quiet_NaN();
  const std::string path = TempPath("invalid.ply");
  absl::Status st = WriteGaussianPly(bad, path);
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StartsWith(st.message(), path)) << st.message();
  struct stat sb;
  EXPECT_NE(::stat(path.c_str(), &sb), 0);

  bad = RandomStore(4, 1, false, 9);
  bad.sh.pop_back();  // size mismatch
  EXPECT_FALSE(WriteGaussianPly(bad, path).ok());

  // Nonexistent directory: the temp file cannot be created.
  const std::string no_dir = TempPath("no_such_dir/x.ply");
  st = WriteGaussianPly(RandomStore(2, 0, false, 1), no_dir);
  EXPECT_FALSE(st.ok());
  EXPECT_TRUE(absl::StartsWith(st.message(), no_dir)) << st.message();

  // Target is a directory: rename fails after the temp file was written; it must be removed.
  const std::string dir_target = TempPath("dir_target");
  ASSERT_EQ(::mkdir(dir_target.c_str(), 0755), 0);
  st = WriteGaussianPly(RandomStore(2, 0, false, 1), dir_target);
  EXPECT_FALSE(st.ok());
  const std::string stem = dir_target.substr(dir_target.find_last_of('/') + 1);
  EXPECT_FALSE(TempFilesLeft(dir_target.substr(0, dir_target.find_last_of('/')), stem));
  ::rmdir(dir_target.c_str());
}

}  // namespace
}  // namespace streetsim
