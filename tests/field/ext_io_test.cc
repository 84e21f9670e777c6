// field_ext.bin and the extended field's checkpoints (scene/field/extended/extended_io.h), the
// deformed store of a loaded extended scene, and the shared-pointer bundle render / eval use.
#include <unistd.h>

#include <cstring>
#include <limits>
#include <filesystem>
#include <fstream>
#include <string>

#include "gtest/gtest.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/extended/extended_io.h"
#include "scene/common/checked_file.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

std::string TempPath(const std::string& name) {
  return (std::filesystem::path(::testing::TempDir()) /
          ("ext_io_" + std::to_string(getpid()) + "_" +
           ::testing::UnitTest::GetInstance()->current_test_info()->name() + "_" + name))
      .string();
}

ExtendedField MakeField(uint64_t seed) {
  absl::StatusOr<DeformationField> base =
      DeformationField::Create(testing::SmallConfig(), testing::TestAabb(), {1000, 2000000}, seed);
  EXPECT_TRUE(base.ok());
  absl::StatusOr<ExtendedField> f = ExtendedField::Create(std::move(*base), ExtendedFieldConfig::AllOn(), seed);
  EXPECT_TRUE(f.ok()) << f.status();
  for (size_t i = 0; i < f->params().size(); ++i) f->mutable_params()[i] += 0.01f * static_cast<float>(i % 7);
  return std::move(*f);
}

TEST(ExtendedFieldIo, RoundTripsFieldAndCheckpoint) {
  const ExtendedField f = MakeField(1);
  const std::string path = TempPath("field_ext.bin");
  ASSERT_TRUE(SaveExtendedField(f, path).ok());
  absl::StatusOr<ExtendedField> g = LoadExtendedField(path, f.base());
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_EQ(g->params(), f.params());
  EXPECT_EQ(g->config().ModulesString(), f.config().ModulesString());
  EXPECT_EQ(g->config().window_dt, f.config().window_dt);
  ExtAdamState adam;
  EXPECT_EQ(LoadExtendedCheckpoint(path, f.base(), &adam).status().code(), absl::StatusCode::kFailedPrecondition);

  ExtAdamState a;
  a.m.assign(f.params().size(), 0.5f);
  a.v.assign(f.params().size(), 0.25f);
  a.step = 17;
  const std::string ck = TempPath("ck_ext.bin");
  ASSERT_TRUE(SaveExtendedCheckpoint(f, a, ck).ok());
  absl::StatusOr<ExtendedField> h = LoadExtendedCheckpoint(ck, f.base(), &adam);
  ASSERT_TRUE(h.ok()) << h.status();
  EXPECT_EQ(adam.step, 17);
  EXPECT_EQ(adam.m, a.m);
  EXPECT_EQ(adam.v, a.v);
  EXPECT_TRUE(LoadExtendedField(ck, f.base()).ok());  // the extension alone can be read from a checkpoint
  std::filesystem::remove(path);
  std::filesystem::remove(ck);
}

TEST(ExtendedFieldIo, DamageAndMismatchAreDataLoss) {
  const ExtendedField f = MakeField(2);
  const std::string path = TempPath("field_ext.bin");
  ASSERT_TRUE(SaveExtendedField(f, path).ok());
  std::string bytes;
  {
    std::ifstream in(path, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  auto write = [&](const std::string& b) {
    std::ofstream out(path, std::ios::binary | std::ios::trunc);
    out.write(b.data(), static_cast<std::streamsize>(b.size()));
  };
  std::string flipped = bytes;
  flipped[bytes.size() / 2] ^= 0x10;
  write(flipped);
  EXPECT_EQ(LoadExtendedField(path, f.base()).status().code(), absl::StatusCode::kDataLoss);
  write(bytes.substr(0, bytes.size() - 9));
  EXPECT_EQ(LoadExtendedField(path, f.base()).status().code(), absl::StatusCode::kDataLoss);
  std::string magic = bytes;
  magic[0] = 'X';
  write(magic);
  EXPECT_EQ(LoadExtendedField(path, f.base()).status().code(), absl::StatusCode::kDataLoss);
  // Another run's field.bin: the base checksum differs.
  write(bytes);
  DeformationField other = f.base();
  other.mutable_params()[3] += 1.0f;
  const absl::Status s = LoadExtendedField(path, other).status();
  EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(std::string(s.message()).find("does not belong"), std::string::npos) << s;
  EXPECT_EQ(LoadExtendedField(TempPath("missing.bin"), f.base()).status().code(), absl::StatusCode::kNotFound);
  std::filesystem::remove(path);
}

TEST(ExtendedFieldIo, DilatedBranchIsVersion2AndVersion1StaysAsItWas) {
  // Without the dilated branch: version 1 (what older readers read); with it: version 2 carrying d.
  auto version_of = [](const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::string b((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    uint32_t v = 0;
    if (b.size() >= 12) std::memcpy(&v, b.data() + 8, 4);
    return v;
  };
  ExtendedFieldConfig c = ExtendedFieldConfig::AllOn();
  c.decoder_max_dlog_scale = 0;  // the decoder unbounded, as before version 3
  absl::StatusOr<ExtendedField> plain = ExtendedField::Create(MakeField(4).base(), c, 4);
  ASSERT_TRUE(plain.ok()) << plain.status();
  const std::string p1 = TempPath("v1.bin");
  ASSERT_TRUE(SaveExtendedField(*plain, p1).ok());
  EXPECT_EQ(version_of(p1), 1u);
  c.vae_dilation = 2;
  absl::StatusOr<ExtendedField> dil = ExtendedField::Create(plain->base(), c, 9);
  ASSERT_TRUE(dil.ok()) << dil.status();
  const std::string p2 = TempPath("v2.bin");
  ASSERT_TRUE(SaveExtendedField(*dil, p2).ok());
  EXPECT_EQ(version_of(p2), 2u);
  absl::StatusOr<ExtendedField> back = LoadExtendedField(p2, plain->base());
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->config().vae_dilation, 2);
  EXPECT_EQ(back->config().ModulesString(), "encoder,vae_dilated,temporal,attention,gru,decoder");
  EXPECT_EQ(back->params(), dil->params());
  // A version-2 file relabelled version 1 (one field too many for it): refused, never misread.
  std::string bytes;
  {
    std::ifstream in(p2, std::ios::binary);
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  bytes[8] = 1;
  {
    std::ofstream out(p2, std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  }
  EXPECT_EQ(LoadExtendedField(p2, plain->base()).status().code(), absl::StatusCode::kDataLoss);
  std::filesystem::remove(p1);
  std::filesystem::remove(p2);
}

TEST(ExtendedFieldIo, DecoderBoundIsVersion3AndOlderFilesLoadUnbounded) {
  auto read = [](const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  };
  auto version_of = [&](const std::string& path) {
    const std::string b = read(path);
    uint32_t v = 0;
    if (b.size() >= 12) std::memcpy(&v, b.data() + 8, 4);
    return v;
  };
  // The default config bounds the decoder: version 3, the bound read back.
  const ExtendedField f = MakeField(5);
  ASSERT_EQ(f.config().decoder_max_dlog_scale, kDefaultDecoderMaxDlogScale);
  const std::string p3 = TempPath("v3.bin");
  ASSERT_TRUE(SaveExtendedField(f, p3).ok());
  EXPECT_EQ(version_of(p3), 3u);
  absl::StatusOr<ExtendedField> back = LoadExtendedField(p3, f.base());
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->config().decoder_max_dlog_scale, kDefaultDecoderMaxDlogScale);
  EXPECT_EQ(back->params(), f.params());
  // Unbounded: version 1, and it loads unbounded (as every file before version 3 was trained).
  ExtendedFieldConfig c = f.config();
  c.decoder_max_dlog_scale = 0;
  absl::StatusOr<ExtendedField> unbounded = ExtendedField::FromParams(f.base(), c, f.params());
  ASSERT_TRUE(unbounded.ok()) << unbounded.status();
  const std::string p1 = TempPath("v1.bin");
  ASSERT_TRUE(SaveExtendedField(*unbounded, p1).ok());
  EXPECT_EQ(version_of(p1), 1u);
  back = LoadExtendedField(p1, f.base());
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->config().decoder_max_dlog_scale, 0.0f);
  // Without the decoder the bound is not written: version 1.
  c = ExtendedFieldConfig::AllOn();
  c.decoder = false;
  absl::StatusOr<ExtendedField> no_decoder = ExtendedField::Create(f.base(), c, 6);
  ASSERT_TRUE(no_decoder.ok()) << no_decoder.status();
  ASSERT_TRUE(SaveExtendedField(*no_decoder, p1).ok());
  EXPECT_EQ(version_of(p1), 1u);
  // A version-3 file relabelled version 2 (a field too many for it), or with a bound out of
  // range: refused, never misread. The checksum is recomputed so that only the content is wrong.
  auto rewrite = [&](std::string bytes) {
    const size_t body = bytes.size() - 8;
    const uint64_t sum = checked_file::Checksum(bytes.data(), body);
    std::memcpy(bytes.data() + body, &sum, 8);
    std::ofstream out(p3, std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  };
  const std::string v3 = read(p3);
  std::string relabelled = v3;
  relabelled[8] = 2;
  rewrite(relabelled);
  EXPECT_EQ(LoadExtendedField(p3, f.base()).status().code(), absl::StatusCode::kDataLoss);
  // The bound sits after the header (16 bytes), the 6 switches and the 8 int32 (7 + dilation).
  const size_t bound_at = 16 + 6 + 8 * 4;
  float stored = 0;
  std::memcpy(&stored, v3.data() + bound_at, 4);
  ASSERT_EQ(stored, kDefaultDecoderMaxDlogScale);
  for (float bad : {-1.0f, 51.0f, std::numeric_limits<float>::quiet_NaN()}) {
    std::string b = v3;
    std::memcpy(b.data() + bound_at, &bad, 4);
    rewrite(b);
    const absl::Status s = LoadExtendedField(p3, f.base()).status();
    EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss) << bad;
    EXPECT_NE(std::string(s.message()).find("Δlog-scale bound"), std::string::npos) << s;
  }
  std::filesystem::remove(p1);
  std::filesystem::remove(p3);
}

TEST(ExtendedFieldShared, DeformedStoreFindsTheExtensionThroughTheBase) {
  const ExtendedField f = MakeField(3);
  GaussianStore g;
  g.sh_degree = 3;
  const size_t n = 20;
  g.means = testing::RandomMeans<float>(n, 3, 5);
  g.log_scales.assign(n * 3, -1.0f);
  g.rotations.assign(n * 4, 0.0f);
  for (size_t i = 0; i < n; ++i) g.rotations[i * 4] = 1.0f;
  g.opacity_logits.assign(n, 0.3f);
  g.sh.assign(n * 48, 0.1f);
  ThreadPool pool(2);
  absl::StatusOr<GaussianStore> direct = ExtDeformedStore(f, g, 1500000, pool);
  ASSERT_TRUE(direct.ok()) << direct.status();
  EXPECT_NE(direct->means, g.means);
  EXPECT_NE(direct->log_scales, g.log_scales);  // the decoder is on
  std::shared_ptr<const DeformationField> shared = ShareWithExtension(f);
  std::shared_ptr<const ExtendedField> found = ExtensionOf(*shared);
  ASSERT_NE(found, nullptr);
  EXPECT_EQ(found->params(), f.params());
  EXPECT_EQ(ExtensionOf(f.base()), nullptr);  // a plain field (not shared with an extension)
  const DeformationField* key = shared.get();
  found.reset();
  shared.reset();
  EXPECT_EQ(ExtensionOf(*key), nullptr);  // gone with its last owner (the address is only compared)
}

}  // namespace
}  // namespace streetsim::field
