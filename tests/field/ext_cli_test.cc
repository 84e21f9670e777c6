// streetsim train --field extended (docs/field.md "Extended field"): a few fine iterations on the
// shared KITTI clip with every module, what the scene directory holds, eval and render of the
// result (through field_ext.bin), resume, the strict ablation end to end (--field-modules none
// writes the same scene as --field s3gaussian), and bad values.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "scene/field/field_io.h"
#include "tests/common/cli_runner.h"

namespace {

using streetsim::cli_test::kKitti;
using streetsim::cli_test::kKittiCamera;
using streetsim::cli_test::Result;
using streetsim::cli_test::RunStreetsim;
using streetsim::cli_test::Slurp;

std::string Dir(const std::string& name) {
  return (std::filesystem::temp_directory_path() /
          ("streetsim_ext_cli_" + std::to_string(getpid()) + "_" + name)).string();
}

Result RunCli(const std::string& args) {
  const std::string out = Dir("out.txt"), err = Dir("err.txt");
  Result r = RunStreetsim(args, out, err);
  std::filesystem::remove(out);
  std::filesystem::remove(err);
  return r;
}

const std::string kSmall =
    " --field-size small --field-motion-prior 0 --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 3 --no-lidar-loss";

TEST(CliExtendedField, TrainEvalRenderResume) {
  const std::string dir = Dir("scene");
  std::filesystem::remove_all(dir);
  Result r = RunCli("train --log " + kKitti + " --out " + dir +
                    " --iterations 12 --field extended --static-iterations 8 --checkpoint-every 10" + kSmall);
  ASSERT_EQ(r.code, 0) << r.err;
  for (const char* f : {"scene.ply", "field.bin", "field_ext.bin", "checkpoint_field_12.bin",
                        "checkpoint_field_12_ext.bin"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + f)) << f;
  }
  EXPECT_FALSE(std::filesystem::exists(dir + "/checkpoint_field_10_ext.bin"));  // replaced by the last one
  // train_meta.json names the field kind and its modules (was "s3gaussian" for an extended run).
  const nlohmann::json meta = nlohmann::json::parse(Slurp(dir + "/train_meta.json"));
  EXPECT_EQ(meta["field"], "extended");
  EXPECT_TRUE(meta["field_modules"].is_string() && !meta["field_modules"].get<std::string>().empty()) << meta.dump();
  // `all` includes the decoder: its Δlog-scale bound, the default ln 10.
  EXPECT_NEAR(meta["field_decoder_max_dlog_scale"].get<double>(), std::log(10.0), 1e-6) << meta.dump();

  r = RunCli("eval --scene " + dir + " --log " + kKitti + " --no-lidar");
  ASSERT_EQ(r.code, 0) << r.err;
  const nlohmann::json j = nlohmann::json::parse(r.out);
  EXPECT_TRUE(j["mean"]["psnr"].is_number());
  EXPECT_TRUE(j["mean"]["psnr_dynamic"].is_number());

  const std::string png = dir + "/r.png";
  r = RunCli("render --scene " + dir + " --camera " + kKittiCamera + " --out-rgb " + png);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(Slurp(png).empty());

  // Resume continues the fine stage (both checkpoints); another field kind is refused.
  r = RunCli("train --log " + kKitti + " --out " + dir +
             " --iterations 13 --field extended --static-iterations 8 --resume" + kSmall);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_TRUE(std::filesystem::exists(dir + "/checkpoint_field_13_ext.bin"));
  r = RunCli("train --log " + kKitti + " --out " + dir +
             " --iterations 18 --field s3gaussian --static-iterations 8 --resume" + kSmall);
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("--field extended"), std::string::npos) << r.err;

  // A damaged field_ext.bin is a clear error, never the base field alone.
  std::string bytes = Slurp(dir + "/field_ext.bin");
  bytes[bytes.size() / 2] ^= 0x20;
  std::ofstream(dir + "/field_ext.bin", std::ios::binary | std::ios::trunc) << bytes;
  r = RunCli("eval --scene " + dir + " --log " + kKitti + " --no-lidar");
  EXPECT_NE(r.code, 0);
  EXPECT_NE(r.err.find("field_ext.bin"), std::string::npos) << r.err;
  std::filesystem::remove_all(dir);
}

TEST(CliExtendedField, NoModulesIsS3Gaussian) {
  // Not bit-identical (the extended field multiplies the plane samples in another order and runs
  // the MLP in other row chunks): equal to float rounding after a few fine iterations.
  const std::string a = Dir("none"), b = Dir("s3");
  const std::string common = " --iterations 11 --static-iterations 8 --deterministic" + kSmall;
  Result r = RunCli("train --log " + kKitti + " --out " + a + " --field extended --field-modules none" + common);
  ASSERT_EQ(r.code, 0) << r.err;
  r = RunCli("train --log " + kKitti + " --out " + b + " --field s3gaussian" + common);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_FALSE(std::filesystem::exists(b + "/field_ext.bin"));
  EXPECT_EQ(nlohmann::json::parse(Slurp(a + "/train_meta.json"))["field_modules"], "none");
  EXPECT_FALSE(nlohmann::json::parse(Slurp(b + "/train_meta.json")).contains("field_modules"));
  absl::StatusOr<streetsim::field::DeformationField> fa = streetsim::field::LoadField(a + "/field.bin");
  absl::StatusOr<streetsim::field::DeformationField> fb = streetsim::field::LoadField(b + "/field.bin");
  ASSERT_TRUE(fa.ok() && fb.ok());
  ASSERT_EQ(fa->params().size(), fb->params().size());
  double num = 0, den = 0;
  for (size_t i = 0; i < fa->params().size(); ++i) {
    const double d = fa->params()[i] - fb->params()[i];
    num += d * d;
    den += double(fb->params()[i]) * fb->params()[i];
  }
  EXPECT_LT(std::sqrt(num / den), 1e-4);
  std::filesystem::remove_all(a);
  std::filesystem::remove_all(b);
}

TEST(CliExtendedField, BadValuesExitTwo) {
  const std::string train = "train --log " + kKitti + " --out " + Dir("bad") + " --iterations 20 --static-iterations 5";
  for (const std::string& args : {
           train + " --field extended --field-modules vae,bogus",
           train + " --field extended --field-modules ''",
           train + " --field s3gaussian --field-modules vae",
           train + " --field bogus",
       }) {
    const Result r = RunCli(args);
    EXPECT_EQ(r.code, 2) << args << ": " << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << args << ": " << r.err;
  }
}

}  // namespace
