// scripts/ablate-field (docs/field.md "Ablation") at a tiny budget on the shared KITTI clip: the rows
// it promises with finite metrics, fine rows that really ran a fine stage from the shared warm-up,
// --resume-rows skipping finished rows, a failing row recorded while the others run, bad input.
#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"
#include "tests/common/scratch_dir.h"

namespace {

using streetsim::cli_test::kBinary;
using streetsim::cli_test::kKitti;
using streetsim::cli_test::Result;
using streetsim::cli_test::Slurp;

const std::string kScript = std::string(STREETSIM_SOURCE_DIR) + "/scripts/ablate-field";
const std::string kBench = std::string(STREETSIM_BINARY_DIR) + "/bench/field_ext_bench";

// Runs the script with Debian's python3; stdout / stderr go to files in dir.
Result RunScript(const std::string& dir, const std::string& args) {
  const std::string out = dir + "/script_out.txt", err = dir + "/script_err.txt";
  const int status =
      std::system(("/usr/bin/python3 " + kScript + " " + args + " >" + out + " 2>" + err).c_str());
  return Result{WEXITSTATUS(status), Slurp(out), Slurp(err)};
}

// The tiny budget of every run here (the shared warm-up is reused when these do not change), with
// `more` options; then the flags passed through to streetsim train.
std::string Tiny(const std::string& work, const std::string& more = "") {
  const std::string bench = std::filesystem::exists(kBench)
                                ? " --field-ext-bench " + kBench + " --bench-gaussians 1000 --bench-repeats 1"
                                : " --no-bench";
  return "--log " + kKitti + " --work " + work +
         " --resolution-scale 0.12 --field-size small --static-iterations 8 --fine-iterations 4" + bench + more +
         " -- --voxel 0.5";
}

const nlohmann::json* FindRow(const nlohmann::json& j, const std::string& name) {
  for (const nlohmann::json& r : j["rows"]) {
    if (r["name"] == name) return &r;
  }
  return nullptr;
}

bool Finite(const nlohmann::json& v) { return v.is_number() && std::isfinite(v.get<double>()); }

TEST(AblateFieldScript, BadInputExits2) {
  const std::string dir = streetsim::testing::ScratchDir("ablate_field_script", "bad");
  Result r = RunScript(dir, Tiny(dir + "/w", " --streetsim " + kBinary + " --rows static,bogus"));
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("unknown row 'bogus'"), std::string::npos) << r.err;
  r = RunScript(dir, Tiny(dir + "/w", " --streetsim " + dir + "/no_such_cli"));
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("no streetsim CLI"), std::string::npos) << r.err;
  r = RunScript(dir, Tiny(dir + "/w", " --streetsim " + kBinary) + " --iterations 5");
  EXPECT_EQ(r.code, 2) << r.err;  // a managed train flag passed through
  EXPECT_NE(r.err.find("--iterations cannot be passed through"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(dir + "/w/static")) << "bad input must not start training";
}

TEST(AblateFieldScript, RowsRunResumeAndRecordFailures) {
  const std::string work = streetsim::testing::ScratchDir("ablate_field_script", "rows");
  const std::string json_path = work + "/out/ablation.json", md_path = work + "/out/ablation.md";
  const std::string outs = " --streetsim " + kBinary + " --out-json " + json_path + " --out-md " + md_path;

  // 1. Two fine rows from one warm-up.
  Result r = RunScript(work, Tiny(work, outs + " --rows s3gaussian,decoder"));
  ASSERT_EQ(r.code, 0) << r.err;
  nlohmann::json j = nlohmann::json::parse(Slurp(json_path));
  ASSERT_EQ(j["rows"].size(), 2u);
  EXPECT_NE(j["header"][0].get<std::string>().find("REDUCED BUDGET"), std::string::npos) << j["header"];
  for (const char* name : {"s3gaussian", "decoder"}) {
    const nlohmann::json* row = FindRow(j, name);
    ASSERT_NE(row, nullptr) << name;
    EXPECT_EQ((*row)["status"], "ok") << (*row)["error"];
    for (const char* split : {"heldout", "train_views"}) {
      EXPECT_TRUE(Finite((*row)[split]["psnr"])) << name << " " << split;
      EXPECT_TRUE(Finite((*row)[split]["ssim"])) << name << " " << split;
    }
    EXPECT_TRUE(Finite((*row)["heldout"]["psnr_dynamic"])) << name;  // the clip has moving vehicles
    EXPECT_TRUE(Finite((*row)["train_run"]["wall_s"])) << name;
    EXPECT_EQ((*row)["train_run"]["field_ran_on"], "cpu") << name;  // --field-device auto, cpu backend
    // A fine stage from the warm-up's iteration 8 to 12.
    const std::string d = (*row)["dir"];
    const nlohmann::json meta = nlohmann::json::parse(Slurp(d + "/train_meta.json"));
    EXPECT_EQ(meta["iterations"], 12) << name;
    EXPECT_EQ(meta["static_iterations"], 8) << name;
    EXPECT_TRUE(std::filesystem::exists(d + "/field.bin")) << name;
    EXPECT_EQ(std::filesystem::exists(d + "/field_ext.bin"), std::string(name) == "decoder") << name;
    EXPECT_NE(Slurp(d + "/train.log").find("iteration 9: fine stage"), std::string::npos) << name;
  }
  if (std::filesystem::exists(kBench)) {
    const int64_t s3g_macs = (*FindRow(j, "s3gaussian"))["serving"]["macs_per_gaussian"];
    const int64_t dec_macs = (*FindRow(j, "decoder"))["serving"]["macs_per_gaussian"];
    EXPECT_GT(s3g_macs, 0);
    EXPECT_GT(dec_macs, s3g_macs);  // the decoder's heads cost multiply-adds
  }
  const std::string md = Slurp(md_path);
  EXPECT_NE(md.find("| s3gaussian |"), std::string::npos) << md;
  EXPECT_NE(md.find("| extended: decoder |"), std::string::npos) << md;
  EXPECT_EQ(r.out, md);
  const auto field_time = std::filesystem::last_write_time(work + "/rows/s3gaussian/field.bin");

  // 2. --resume-rows: the finished rows are skipped, the warm-up reused, the new static row runs.
  r = RunScript(work, Tiny(work, outs + " --rows static,s3gaussian,decoder --resume-rows"));
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("static warm-up: reusing"), std::string::npos) << r.err;
  j = nlohmann::json::parse(Slurp(json_path));
  ASSERT_EQ(j["rows"].size(), 3u);
  EXPECT_EQ((*FindRow(j, "s3gaussian"))["skipped"], true);
  EXPECT_EQ((*FindRow(j, "decoder"))["skipped"], true);
  EXPECT_EQ(std::filesystem::last_write_time(work + "/rows/s3gaussian/field.bin"), field_time);
  const nlohmann::json& st = *FindRow(j, "static");
  EXPECT_EQ(st["skipped"], false);
  EXPECT_EQ(st["status"], "ok") << st["error"];
  EXPECT_TRUE(Finite(st["heldout"]["psnr"]));
  const nlohmann::json static_meta = nlohmann::json::parse(Slurp(work + "/rows/static/train_meta.json"));
  EXPECT_EQ(static_meta["iterations"], 12);
  EXPECT_EQ(static_meta["field"], "static");
  EXPECT_FALSE(std::filesystem::exists(work + "/rows/static/field.bin"));

  // 3. A row whose training fails: recorded in the table, the other rows still reported, exit 1.
  const std::string wrapper = work + "/failing_streetsim";
  {
    std::ofstream w(wrapper);
    w << "#!/bin/sh\ncase \" $* \" in *\" --field-modules gru \"*) echo 'streetsim train: injected failure' >&2; "
         "exit 1;; esac\nexec " << kBinary << " \"$@\"\n";
  }
  std::filesystem::permissions(wrapper, std::filesystem::perms::owner_all);
  r = RunScript(work, Tiny(work, " --streetsim " + wrapper + " --out-json " + json_path + " --out-md " + md_path +
                                     " --rows s3gaussian,gru --resume-rows"));
  EXPECT_EQ(r.code, 1) << r.err;
  j = nlohmann::json::parse(Slurp(json_path));
  ASSERT_EQ(j["rows"].size(), 2u);
  EXPECT_EQ((*FindRow(j, "s3gaussian"))["status"], "ok");
  const nlohmann::json& gru = *FindRow(j, "gru");
  EXPECT_EQ(gru["status"], "failed");
  EXPECT_NE(gru["error"].get<std::string>().find("injected failure"), std::string::npos) << gru["error"];
  EXPECT_NE(Slurp(md_path).find("FAILED: train exit 1: streetsim train: injected failure"), std::string::npos);
}

}  // namespace
