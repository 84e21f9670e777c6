// field.bin: lossless round trips (with and without Adam moments), atomic writes, and a clear
// error for every kind of damaged file.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include "gtest/gtest.h"
#include "scene/field/field_io.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

namespace fs = std::filesystem;

std::string TempDir(const char* name) {
  const fs::path d = fs::path(STREETSIM_BINARY_DIR) / "tests" / "field" / name;
  fs::remove_all(d);
  fs::create_directories(d);
  return d.string();
}

DeformationField MakeField() {
  FieldConfig c = testing::SmallConfig();
  c.full_time_range = false;
  absl::StatusOr<DeformationField> f = DeformationField::Create(c, testing::TestAabb(), {123, 4'567'890}, 5);
  EXPECT_TRUE(f.ok());
  return std::move(*f);
}

std::string ReadAll(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}
void WriteAll(const std::string& path, const std::string& bytes) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), bytes.size());
}

TEST(FieldIo, RoundTripIsExact) {
  const std::string dir = TempDir("io_roundtrip");
  const DeformationField f = MakeField();
  const std::string path = dir + "/" + kFieldFileName;
  ASSERT_TRUE(SaveField(f, path).ok());
  EXPECT_FALSE(fs::exists(path + ".tmp"));
  absl::StatusOr<DeformationField> g = LoadField(path);
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_EQ(g->params(), f.params());
  EXPECT_EQ(g->config().multires, f.config().multires);
  EXPECT_EQ(g->config().full_time_range, false);
  EXPECT_EQ(g->time_range().start_us, 123);
  EXPECT_EQ(g->time_range().end_us, 4'567'890);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(g->aabb().min[k], f.aabb().min[k]);
    EXPECT_EQ(g->aabb().max[k], f.aabb().max[k]);
  }
  // A plain field is not a checkpoint.
  absl::StatusOr<FieldCheckpoint> c = LoadFieldCheckpoint(path);
  EXPECT_EQ(c.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST(FieldIo, CheckpointKeepsAdamMoments) {
  const std::string dir = TempDir("io_checkpoint");
  const DeformationField f = MakeField();
  FieldAdamState adam;
  adam.Init(f.layout().total);
  adam.step = 42;
  for (size_t i = 0; i < adam.m.size(); ++i) {
    adam.m[i] = 0.001f * i;
    adam.v[i] = 1e-6f * i;
  }
  const std::string path = dir + "/field_checkpoint.bin";
  ASSERT_TRUE(SaveFieldCheckpoint(f, adam, path).ok());
  absl::StatusOr<FieldCheckpoint> c = LoadFieldCheckpoint(path);
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->adam.step, 42);
  EXPECT_EQ(c->adam.m, adam.m);
  EXPECT_EQ(c->adam.v, adam.v);
  EXPECT_EQ(c->field.params(), f.params());
  EXPECT_TRUE(LoadField(path).ok());  // the field alone can be read from a checkpoint
  FieldAdamState wrong;
  wrong.Init(3);
  EXPECT_FALSE(SaveFieldCheckpoint(f, wrong, path).ok());
}

TEST(FieldIo, DamagedFilesGiveClearErrors) {
  const std::string dir = TempDir("io_damaged");
  const std::string path = dir + "/field.bin";
  ASSERT_TRUE(SaveField(MakeField(), path).ok());
  const std::string good = ReadAll(path);
  auto load_error = [&](const std::string& bytes) {
    WriteAll(path, bytes);
    absl::StatusOr<DeformationField> f = LoadField(path);
    EXPECT_FALSE(f.ok());
    return std::string(f.status().message());
  };
  std::string flipped = good;
  flipped[good.size() / 2] ^= 0x10;
  EXPECT_NE(load_error(flipped).find("checksum"), std::string::npos);
  EXPECT_NE(load_error(good.substr(0, good.size() - 100)).find("checksum"), std::string::npos);
  EXPECT_NE(load_error(good.substr(0, 12)).find("field"), std::string::npos);
  EXPECT_NE(load_error("hello world, not a field at all").find("not a streetsim field file"), std::string::npos);
  std::string version = good;
  version[8] = 9;
  EXPECT_NE(load_error(version).find("version 9"), std::string::npos);
  EXPECT_EQ(LoadField(dir + "/missing.bin").status().code(), absl::StatusCode::kNotFound);
  EXPECT_FALSE(SaveField(MakeField(), dir + "/no/such/dir/field.bin").ok());
}

}  // namespace
}  // namespace streetsim::field
