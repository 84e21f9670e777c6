// Evaluation metrics as JSON (scene/eval/metrics_json.h): DIR/heldout.json round-trips what the
// trainer measured, nulls stay "not measured", and a damaged file is DataLoss naming it.
#include "scene/eval/metrics_json.h"

#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>

#include "tests/common/scratch_dir.h"

namespace streetsim::train {
namespace {

EvalResult TwoViews() {
  EvalResult r;
  FrameMetrics a;
  a.name = "image_02/0000000003.png";
  a.frame = 3;
  a.psnr = 21.5;
  a.ssim = 0.71;
  a.psnr_dynamic = 19.25;
  a.psnr_static = 21.75;
  FrameMetrics b;
  b.name = "image_02/0000000007.png";
  b.frame = 7;
  b.psnr = 23.5;
  b.ssim = 0.79;
  b.depth_median_abs_m = 0.5;
  b.depth_within_5pct = 0.25;  // a, b: no dynamic pixel in b
  b.psnr_static = 23.5;
  r.frames = {a, b};
  r.mean.psnr = 22.5;
  r.mean.ssim = 0.75;
  r.mean.psnr_dynamic = 19.25;
  r.mean.psnr_static = 22.625;
  return r;
}

TEST(MetricsJson, HeldoutFileRoundTrips) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_metrics_json", "round_trip");
  ASSERT_TRUE(WriteHeldoutMetrics(dir, TwoViews()).ok());
  const nlohmann::json j = nlohmann::json::parse(std::ifstream(dir + "/heldout.json"));
  EXPECT_EQ(j["views"], 2);
  EXPECT_TRUE(j["frames"][1]["psnr_dynamic"].is_null());
  EXPECT_TRUE(j["frames"][0]["depth_median_abs_m"].is_null());
  EXPECT_EQ(j["frames"][1]["frame"], 7);
  absl::StatusOr<EvalResult> back = ReadHeldoutMetrics(dir);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->frames.size(), 2u);
  EXPECT_EQ(back->frames[0].name, "image_02/0000000003.png");
  EXPECT_EQ(back->frames[0].frame, 3);
  EXPECT_DOUBLE_EQ(back->frames[0].psnr, 21.5);
  EXPECT_DOUBLE_EQ(back->frames[0].psnr_dynamic, 19.25);
  EXPECT_DOUBLE_EQ(back->frames[0].depth_median_abs_m, -1);
  EXPECT_DOUBLE_EQ(back->frames[1].psnr_dynamic, -1);
  EXPECT_DOUBLE_EQ(back->frames[1].depth_within_5pct, 0.25);
  EXPECT_DOUBLE_EQ(back->mean.psnr, 22.5);
  EXPECT_DOUBLE_EQ(back->mean.ssim, 0.75);
  EXPECT_DOUBLE_EQ(back->mean.psnr_static, 22.625);
}

TEST(MetricsJson, MissingAndDamagedFiles) {
  const std::string dir = streetsim::testing::ScratchDir("streetsim_metrics_json", "damaged");
  EXPECT_EQ(ReadHeldoutMetrics(dir).status().code(), absl::StatusCode::kNotFound);
  for (const char* text : {"{\"views\": 1, \"frames\": [", "[1, 2]", "{\"frames\": [], \"mean\": {\"psnr\": 1}}",
                           "{\"frames\": [{\"psnr\": 1, \"ssim\": 0.5}], \"mean\": {\"psnr\": 1, \"ssim\": 0.5}}",
                           "{\"frames\": [{\"frame\": 3, \"psnr\": \"high\", \"ssim\": 0.5}], \"mean\": {}}"}) {
    std::ofstream(dir + "/heldout.json") << text;
    const absl::Status s = ReadHeldoutMetrics(dir).status();
    EXPECT_EQ(s.code(), absl::StatusCode::kDataLoss) << text;
    EXPECT_NE(s.message().find("heldout.json"), std::string::npos) << s;
  }
}

}  // namespace
}  // namespace streetsim::train
