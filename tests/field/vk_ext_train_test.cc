// The fine stage of --field extended with the field on Vulkan (FieldOptions::device kVulkan,
// forced onto whatever Vulkan device exists; lavapipe here) trains like the cpu run: every module
// on, the moving-cluster scene of tests/train/synthetic_scene.h, 20 fine iterations; the trained
// base field (field.bin), the extension (field_ext.bin) and the held-out PSNR agree to the drift
// of float rounding. Skips without a Vulkan device.
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/field_io.h"
#include "scene/train/trainer.h"
#include "tests/common/scratch_dir.h"
#include "tests/train/synthetic_scene.h"

namespace streetsim::train {
namespace {

// |a - b| / |a - init|: how far apart the runs ended compared with how far training moved.
double Drift(const std::vector<float>& a, const std::vector<float>& b, const std::vector<float>& init) {
  double diff = 0, moved = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    diff += double(a[i] - b[i]) * (a[i] - b[i]);
    moved += double(a[i] - init[i]) * (a[i] - init[i]);
  }
  EXPECT_GT(moved, 0.0);
  return std::sqrt(diff / moved);
}

TEST(VulkanExtendedTraining, TracksTheCpuRun) {
  if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device";
  const synthetic::MovingClusterRun scene = synthetic::MovingClusterViews();
  std::vector<float> base[2], ext[2];
  double psnr[2] = {0, 0};
  TrainOptions opt = synthetic::MovingClusterOptions(FieldMode::kS3Gaussian, "all");
  opt.iterations = 120;  // 100 static, 20 fine (lavapipe: ~0.6 s per fine iteration with every module)
  ASSERT_TRUE(opt.field.extended.has_value());
  for (int k = 0; k < 2; ++k) {
    opt.field.device = k == 0 ? FieldDevice::kCpu : FieldDevice::kVulkan;
    const std::string dir = testing::ScratchDir("streetsim_vk_ext_train", k == 0 ? "cpu" : "vulkan");
    absl::StatusOr<TrainResult> r = TrainOnViews(scene.train, &scene.start, scene.test, dir, opt);
    ASSERT_TRUE(r.ok()) << r.status();
    psnr[k] = r->heldout.mean.psnr;
    absl::StatusOr<field::DeformationField> f = field::LoadField(dir + "/field.bin");
    ASSERT_TRUE(f.ok()) << f.status();
    base[k] = f->params();
    absl::StatusOr<field::ExtendedField> e =
        field::LoadExtendedField(dir + "/" + field::kExtendedFieldFileName, *std::move(f));
    ASSERT_TRUE(e.ok()) << e.status();
    ext[k] = e->params();
  }
  ASSERT_EQ(base[0].size(), base[1].size());
  ASSERT_EQ(ext[0].size(), ext[1].size());
  // The initial parameters, as DynamicStage::Begin makes them.
  const uint64_t seed = opt.field.seed + opt.seed;
  absl::StatusOr<field::DeformationField> init =
      field::DeformationField::Create(opt.field.config, AabbOfMeans(scene.start.means), {0, 1}, seed);
  ASSERT_TRUE(init.ok()) << init.status();
  const std::vector<float> base_init = init->params();
  absl::StatusOr<field::ExtendedField> ext_init =
      field::ExtendedField::Create(*std::move(init), *opt.field.extended, seed + 0x9e37);
  ASSERT_TRUE(ext_init.ok()) << ext_init.status();
  // Adam's normalised steps turn rounding-level differences of near-zero gradients (float atomics
  // on the device, other summation orders) into lr-sized steps, so the runs drift apart slowly; a
  // wrong gradient would be as large as the movement (the base field's test: same bound).
  const double db = Drift(base[0], base[1], base_init), de = Drift(ext[0], ext[1], ext_init->params());
  std::fprintf(stderr,
               "extended field on cpu vs vulkan: |difference| / |training's movement| base %.3g, extension %.3g, "
               "held-out %.2f vs %.2f dB\n",
               db, de, psnr[0], psnr[1]);
  EXPECT_LT(db, 0.05);
  EXPECT_LT(de, 0.05);
  EXPECT_NEAR(psnr[0], psnr[1], 0.2);
}

}  // namespace
}  // namespace streetsim::train
