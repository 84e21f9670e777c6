// `streetsim train --field s3gaussian --deterministic` twice, in two processes: the outputs must
// be the same bytes (docs/training.md "Reproducibility"). The runs differ in what should not
// matter: thread count (STREETSIM_THREADS 1 vs 2) and the output path's length, which moves the
// heap blocks the field's scratch lands in (their alignment once changed the bias gradients'
// last bits; tests/field/field_bits_test.cc checks that part in one process).
#include <cstdlib>
#include <string>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"
#include "tests/common/scratch_dir.h"

namespace {

using streetsim::cli_test::kKitti;
using streetsim::cli_test::Result;
using streetsim::cli_test::RunStreetsim;
using streetsim::cli_test::Slurp;

TEST(CliFieldRepro, TwoDeterministicRunsWriteTheSameBytes) {
  const std::string root = streetsim::testing::ScratchDir("streetsim_cli_field_repro", "runs");
  const std::string dirs[2] = {root + "/a", root + "/bbbbb"};
  const char* threads[2] = {"1", "2"};
  for (int i = 0; i < 2; ++i) {
    setenv("STREETSIM_THREADS", threads[i], 1);  // inherited by the helper's shell
    const Result r = RunStreetsim("train --log " + kKitti + " --out " + dirs[i] +
                                      " --iterations 24 --field s3gaussian --static-iterations 6 --field-size small --field-motion-prior 0"
                                      " --resolution-scale 0.12 --holdout-every 10 --voxel 0.5 --seed 5"
                                      " --deterministic",
                                  root + "/out" + std::to_string(i) + ".txt", root + "/err" + std::to_string(i) + ".txt");
    unsetenv("STREETSIM_THREADS");
    ASSERT_EQ(r.code, 0) << "STREETSIM_THREADS=" << threads[i] << ": " << r.err;
  }
  for (const char* f : {"field.bin", "checkpoint_field_24.bin", "checkpoint.bin", "scene.ply"}) {
    const std::string a = Slurp(dirs[0] + "/" + f), b = Slurp(dirs[1] + "/" + f);
    ASSERT_FALSE(a.empty()) << f;
    EXPECT_TRUE(a == b) << f << " differs between the two runs";
  }
}

}  // namespace
