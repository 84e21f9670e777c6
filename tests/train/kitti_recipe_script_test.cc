// scripts/kitti-recipe (docs/benchmarks.md "Where the held-out error is", session 25) drives a fake
// `streetsim` that records its arguments: the real schedule takes hours. What is held here is the
// schedule itself (segment ends and the flags of each), that a finished directory is left alone,
// that a stopped one goes on from the segment after its checkpoint, and that a failing segment or a
// missing clip stops the script with an error.
#include <sys/stat.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"

namespace {

const std::string kScript = std::string(STREETSIM_SOURCE_DIR) + "/scripts/kitti-recipe";

std::string Slurp(const std::string& path) {
  std::ifstream f(path);
  std::stringstream s;
  s << f.rdbuf();
  return s.str();
}

std::vector<std::string> Lines(const std::string& text) {
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

bool Has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

// A fake build directory whose bin/streetsim appends its arguments to `calls`, writes the
// checkpoint record and held-out figures a segment leaves, and fails with exit 2 when the
// segment's end is `fail_at`.
std::string FakeBuild(const std::string& dir, const std::string& calls, int fail_at = -1) {
  std::filesystem::create_directories(dir + "/bin");
  const std::string bin = dir + "/bin/streetsim";
  std::ofstream(bin)
      << "#!/usr/bin/env bash\n"
         "if [ \"$1\" = --help ]; then echo '  train     scene training'; exit 0; fi\n"
         "echo \"$*\" >> "
      << calls
      << "\n"
         "out=; it=0\n"
         "while [ $# -gt 0 ]; do case $1 in --out) out=$2; shift;; --iterations) it=$2; shift;; "
         "esac; shift; done\n"
         "if [ \"$it\" = "
      << fail_at
      << " ]; then echo 'streetsim train: boom' >&2; exit 2; fi\n"
         "printf '{\\n  \"field\": \"x\",\\n  \"iteration\": %s\\n}\\n' \"$it\" > \"$out/checkpoint.json\"\n"
         "touch \"$out/checkpoint.bin\"\n"
         "printf '{\"frames\": [], \"mean\": {\"psnr\": %s.5, \"ssim\": 0.9}}' \"$it\" > "
         "\"$out/heldout.json\"\n";
  chmod(bin.c_str(), 0755);
  return dir;
}

struct ScriptResult {
  int code;
  std::string out, err;
};

ScriptResult RunRecipe(const std::string& build, const std::string& out_dir,
                       const std::string& data_dir = STREETSIM_DATA_DIR) {
  const std::string out = out_dir + ".stdout", err = out_dir + ".stderr";
  const std::string cmd = "BUILD_DIR=" + build + " STREETSIM_DATA_DIR=" + data_dir + " " + kScript + " " + out_dir +
                          " >" + out + " 2>" + err;
  const int status = std::system(cmd.c_str());
  return ScriptResult{WEXITSTATUS(status), Slurp(out), Slurp(err)};
}

TEST(KittiRecipeScript, RunsTheMeasuredScheduleAndResumes) {
  const std::string dir = streetsim::testing::ScratchDir("kitti_recipe_script", "schedule");
  const std::string calls = dir + "/calls.txt";
  const std::string build = FakeBuild(dir + "/build", calls);
  const std::string out = dir + "/run";
  ScriptResult r = RunRecipe(build, out);
  ASSERT_EQ(r.code, 0) << r.err;
  const std::vector<std::string> segments = Lines(Slurp(calls));
  const std::vector<int> ends = {5000, 6010, 7510, 8010, 8510, 9010, 9510, 10010, 10510, 11010, 11510, 12010, 12510};
  ASSERT_EQ(segments.size(), ends.size()) << Slurp(calls);
  for (size_t i = 0; i < ends.size(); ++i) {
    const std::string& s = segments[i];
    SCOPED_TRACE(s);
    EXPECT_TRUE(Has(s, "--iterations " + std::to_string(ends[i])));
    EXPECT_TRUE(Has(s, "--out " + out));
    EXPECT_TRUE(Has(s, "--holdout-every 4 --seed 0"));
    EXPECT_TRUE(Has(s, "--pose-refinement --pose-refine-from 300 --pose-refine-until 5000"));
    EXPECT_EQ(Has(s, "--resume"), i > 0);  // the static stage starts the directory
    EXPECT_EQ(Has(s, "--field static"), i == 0);
    EXPECT_EQ(Has(s, "--field s3gaussian --static-iterations 5000 --field-motion-prior 0.3"), i > 0);
    EXPECT_EQ(Has(s, "--field-lr-decay-iterations 4500"), ends[i] > 7510);  // annealed after 2510 fine
    EXPECT_EQ(Has(s, "--densify-until 5000"), ends[i] > 10010);             // ended after 5010 fine
  }
  EXPECT_TRUE(Has(r.out, "held-out at 12510: \"mean\":{\"psnr\":12510.5")) << r.out;

  // Finished: a second call trains nothing.
  r = RunRecipe(build, out);
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_EQ(Lines(Slurp(calls)).size(), ends.size());

  // Stopped inside a segment (a checkpoint at 9200): the next call goes on with that segment.
  std::ofstream(out + "/checkpoint.json") << "{\n  \"iteration\": 9200\n}\n";
  std::filesystem::remove(calls);
  r = RunRecipe(build, out);
  ASSERT_EQ(r.code, 0) << r.err;
  const std::vector<std::string> resumed = Lines(Slurp(calls));
  ASSERT_EQ(resumed.size(), 7u) << Slurp(calls);
  EXPECT_TRUE(Has(resumed[0], "--resume") && Has(resumed[0], "--iterations 9510")) << resumed[0];
}

TEST(KittiRecipeScript, AFailingSegmentOrAMissingClipStopsIt) {
  const std::string dir = streetsim::testing::ScratchDir("kitti_recipe_script", "fail");
  const std::string calls = dir + "/calls.txt";
  const std::string build = FakeBuild(dir + "/build", calls, /*fail_at=*/8510);
  ScriptResult r = RunRecipe(build, dir + "/run");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_TRUE(Has(r.err, "streetsim train: boom")) << r.err;
  EXPECT_EQ(Lines(Slurp(calls)).size(), 5u);  // 5000 ... 8510, nothing after the failure

  r = RunRecipe(build, dir + "/nodata", dir + "/no_such_data");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_TRUE(Has(r.err, "kitti-recipe: no KITTI clip at " + dir + "/no_such_data/kitti_raw")) << r.err;
}

}  // namespace
