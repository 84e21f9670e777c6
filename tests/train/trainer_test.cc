// The trainer on a short real clip: it learns, densification grows and shrinks the scene, and a
// run killed after its last checkpoint resumes to the same bits as an uninterrupted run.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "scene/train/dataset.h"
#include "tests/common/scratch_dir.h"
#include "tests/train/field_stage_fixtures.h"
#include "scene/common/checked_file.h"
#include "scene/log/open_log.h"
#include "scene/field/field_io.h"
#include "scene/train/train_state.h"
#include "scene/train/trainer.h"
#include "render/vulkan/vulkan_engine.h"

namespace streetsim::train {
namespace {

const char* kKitti = STREETSIM_DATA_DIR "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

DriveLog ShortLog(int frames) {
  absl::StatusOr<DriveLog> log = OpenLog(kKitti);
  EXPECT_TRUE(log.ok()) << log.status();
  log->frames.resize(frames);
  return *log;
}

TrainOptions ShortOptions() {
  TrainOptions o;
  o.iterations = 30;
  o.resolution_scale = 0.25;
  o.holdout_every = 4;
  o.seed = 7;
  o.deterministic = true;
  o.checkpoint_every = 10;
  o.write_outputs = false;
  o.init_voxel_m = 0.4;
  o.exposure = true;
  // Densify / reset early so that a 30-iteration run exercises them.
  o.hyper.densify_from = 5;
  o.hyper.densify_interval = 10;
  o.hyper.opacity_reset_interval = 20;
  o.hyper.sh_degree_interval = 10;
  o.hyper.densify_grad_threshold = 0.00005;
  return o;
}

// Empty and absent: the trainer creates its output directory (removed at the end of the run).
std::string TempDir(const std::string& name) {
  const std::string p = testing::ScratchDir("streetsim_trainer_test", name);
  std::filesystem::remove_all(p);
  return p;
}

// A Gaussian large on screen (100 px) but small in the world is kept at the Gaussian cap as below
// it: 3DGS's screen-size prune never fires in its reference (it zeroes the radii when it
// densifies, before it prunes), and here it once fired only at the cap, where it pruned 783k of a
// 2.0M-Gaussian scene at once and the divergence guard stopped the run. The world-size rule stays.
TEST(Densification, TheGaussianCapTurnsOnNoScreenSizePrune) {
  GaussianStore init;
  init.sh_degree = 3;
  init.Resize(8);
  for (size_t i = 0; i < init.size(); ++i) {
    const float mean[3] = {static_cast<float>(i), 0.0f, 5.0f};
    for (int k = 0; k < 3; ++k) {
      init.means[i * 3 + k] = mean[k];
      init.log_scales[i * 3 + k] = std::log(0.05f);
    }
    init.rotations[i * 4] = 1.0f;
    init.opacity_logits[i] = 2.0f;
  }
  const Hyper h;
  const int64_t after_first_reset = h.opacity_reset_interval + 100;
  for (size_t cap : {init.size(), size_t{1000}}) {
    TrainState st = TrainState::Init(init, /*extent=*/10.0, 1, 1);
    std::fill(st.max_radii.begin(), st.max_radii.end(), 100.0f);
    Hyper capped = h;
    capped.max_gaussians = cap;
    size_t added = 0, removed = 0;
    DensifyAndPrune(&st, capped, after_first_reset, &added, &removed);
    EXPECT_EQ(added, 0u) << "cap " << cap;
    EXPECT_EQ(removed, 0u) << "cap " << cap;
    EXPECT_EQ(st.size(), init.size()) << "cap " << cap;
  }
  // Wider than a tenth of the extent (1 m): pruned.
  for (int k = 0; k < 3; ++k) init.log_scales[3 + k] = std::log(2.0f);
  TrainState st = TrainState::Init(init, /*extent=*/10.0, 1, 1);
  size_t added = 0, removed = 0;
  DensifyAndPrune(&st, h, after_first_reset, &added, &removed);
  EXPECT_EQ(removed, 1u);
  EXPECT_EQ(st.size(), init.size() - 1);
}

TEST(Trainer, ResumeAfterKillReachesTheSameBits) {
  const DriveLog log = ShortLog(8);
  const std::string a = TempDir("a"), b = TempDir("b");
  const TrainOptions opt = ShortOptions();
  absl::StatusOr<TrainResult> ra = Train(log, a, opt);
  ASSERT_TRUE(ra.ok()) << ra.status();
  EXPECT_EQ(ra->iterations, 30);

  TrainOptions killed = opt;
  killed.stop_after = 25;  // dies 5 iterations after the checkpoint at 20
  absl::StatusOr<TrainResult> rb = Train(log, b, killed);
  ASSERT_TRUE(rb.ok()) << rb.status();
  absl::StatusOr<TrainState> at20 = LoadCheckpoint(b + "/checkpoint.bin");
  ASSERT_TRUE(at20.ok());
  EXPECT_EQ(at20->iteration, 20);
  TrainOptions resumed = opt;
  resumed.resume = true;
  rb = Train(log, b, resumed);
  ASSERT_TRUE(rb.ok()) << rb.status();

  absl::StatusOr<TrainState> sa = LoadCheckpoint(a + "/checkpoint.bin");
  absl::StatusOr<TrainState> sb = LoadCheckpoint(b + "/checkpoint.bin");
  ASSERT_TRUE(sa.ok() && sb.ok());
  EXPECT_EQ(sa->iteration, 30);
  EXPECT_EQ(sb->iteration, 30);
  EXPECT_EQ(sa->params.means, sb->params.means);
  EXPECT_EQ(sa->params.sh, sb->params.sh);
  EXPECT_EQ(sa->params.opacity_logits, sb->params.opacity_logits);
  EXPECT_EQ(sa->params.log_scales, sb->params.log_scales);
  EXPECT_EQ(sa->params.rotations, sb->params.rotations);
  EXPECT_EQ(sa->adam_v.means, sb->adam_v.means);
  EXPECT_EQ(sa->exposure, sb->exposure);
  EXPECT_EQ(sa->view_queue, sb->view_queue);
  EXPECT_EQ(0, std::memcmp(sa->sky, sb->sky, sizeof(sa->sky)));
}

// A tiny field: the point is the bookkeeping, not the quality.
FieldOptions TinyField(int static_iterations) {
  FieldOptions f = fixtures::TinyFieldOptions(5);
  f.static_iterations = static_iterations;
  return f;
}

// Killed in the fine stage before its first checkpoint (so the resume crosses the stage
// boundary: new field, Gaussian moments re-created), then killed again after a fine-stage
// checkpoint: both resumes reach the bits of an uninterrupted run, field and its Adam included.
TEST(Trainer, FieldResumeAcrossTheStageBoundaryReachesTheSameResult) {
  const DriveLog log = ShortLog(8);
  const std::string a = TempDir("field_a"), b = TempDir("field_b");
  TrainOptions opt = ShortOptions();
  opt.field = TinyField(12);
  absl::StatusOr<TrainResult> ra = Train(log, a, opt);
  ASSERT_TRUE(ra.ok()) << ra.status();
  EXPECT_EQ(ra->iterations, 30);

  TrainOptions killed = opt;
  killed.stop_after = 15;  // checkpoint at 10 (static), fine stage from 13
  ASSERT_TRUE(Train(log, b, killed).ok());
  EXPECT_FALSE(std::filesystem::exists(FieldCheckpointPath(b, 10)));
  killed.resume = true;
  killed.stop_after = 25;  // checkpoint at 20 (fine)
  absl::StatusOr<TrainResult> rb = Train(log, b, killed);
  ASSERT_TRUE(rb.ok()) << rb.status();
  EXPECT_TRUE(std::filesystem::exists(FieldCheckpointPath(b, 20)));
  TrainOptions resumed = opt;
  resumed.resume = true;
  rb = Train(log, b, resumed);
  ASSERT_TRUE(rb.ok()) << rb.status();

  absl::StatusOr<TrainState> sa = LoadCheckpoint(a + "/checkpoint.bin");
  absl::StatusOr<TrainState> sb = LoadCheckpoint(b + "/checkpoint.bin");
  ASSERT_TRUE(sa.ok() && sb.ok());
  EXPECT_EQ(sb->iteration, 30);
  // Bit-identical like the static stage's resume (ResumeAfterKillReachesTheSameBits): the resumed
  // run's field scratch sits at other heap addresses, which once changed the bias gradients'
  // last bits (docs/training.md "Reproducibility").
  EXPECT_EQ(sa->params.means, sb->params.means);
  EXPECT_EQ(sa->params.sh, sb->params.sh);
  EXPECT_EQ(sa->params.opacity_logits, sb->params.opacity_logits);
  EXPECT_EQ(sa->params.log_scales, sb->params.log_scales);
  EXPECT_EQ(sa->adam_m.means, sb->adam_m.means);
  EXPECT_EQ(sa->adam_v.sh, sb->adam_v.sh);
  EXPECT_EQ(sa->adam_step, sb->adam_step);
  EXPECT_EQ(sa->adam_step, 30 - 12 - 1);  // moments re-created at 13; densifying at 22 skips Adam
  EXPECT_EQ(sa->view_queue, sb->view_queue);
  absl::StatusOr<field::FieldCheckpoint> fa = field::LoadFieldCheckpoint(FieldCheckpointPath(a, 30));
  absl::StatusOr<field::FieldCheckpoint> fb = field::LoadFieldCheckpoint(FieldCheckpointPath(b, 30));
  ASSERT_TRUE(fa.ok() && fb.ok()) << fa.status() << fb.status();
  EXPECT_EQ(fa->adam.step, 18);
  EXPECT_EQ(fa->field.params(), fb->field.params());
  EXPECT_EQ(fa->adam.m, fb->adam.m);
  EXPECT_EQ(fa->adam.v, fb->adam.v);
  // The field learned something (its parameters moved from the initial ones).
  absl::StatusOr<field::DeformationField> init = field::DeformationField::Create(
      opt.field.config, fa->field.aabb(), fa->field.time_range(), opt.seed + opt.field.seed);
  ASSERT_TRUE(init.ok());
  EXPECT_NE(init->params(), fa->field.params());
  EXPECT_FALSE(std::filesystem::exists(FieldCheckpointPath(b, 20)));  // older ones removed

  // A changed stage length does not silently pair the field with the wrong Gaussians.
  TrainOptions other = opt;
  other.resume = true;
  other.iterations = 40;
  other.field.static_iterations = 10;
  absl::StatusOr<TrainResult> bad = Train(log, b, other);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kFailedPrecondition) << bad.status();
  // Nor does a static resume drop the field.
  other.field = FieldOptions();
  bad = Train(log, b, other);
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kFailedPrecondition) << bad.status();
}

// The field on Vulkan with its optimiser there (FieldOptions::optimizer kDevice): the field
// checkpoints carry the device's parameters and Adam moments, so that a run killed after a
// fine-stage checkpoint resumes to what an uninterrupted run reaches, and both agree with the
// host optimiser. Not bit-identical (the device sums plane gradients with float atomics): the
// differences are measured against how far training moved the field; a lost moment or a stale
// host copy would be of the movement's order.
TEST(Trainer, VulkanFieldResumesWithItsDeviceOptimizerState) {
  if (ListVulkanDevices().empty()) GTEST_SKIP() << "no Vulkan device";
  const DriveLog log = ShortLog(8);
  TrainOptions opt = ShortOptions();
  opt.field = TinyField(12);
  opt.field.device = FieldDevice::kVulkan;
  opt.field.optimizer = FieldOptimizerPlace::kDevice;  // kAuto would pick the host on lavapipe
  const std::string a = TempDir("vkopt_a"), b = TempDir("vkopt_b"), c = TempDir("vkopt_host");
  TrainOptions with_outputs = opt;
  with_outputs.write_outputs = true;  // field.bin
  ASSERT_TRUE(Train(log, a, with_outputs).ok());
  TrainOptions killed = opt;
  killed.stop_after = 25;  // fine-stage checkpoint at 20
  ASSERT_TRUE(Train(log, b, killed).ok());
  killed.stop_after = 0;
  killed.resume = true;
  ASSERT_TRUE(Train(log, b, killed).ok());
  TrainOptions host = opt;
  host.field.optimizer = FieldOptimizerPlace::kHost;
  ASSERT_TRUE(Train(log, c, host).ok());

  absl::StatusOr<field::FieldCheckpoint> fa = field::LoadFieldCheckpoint(FieldCheckpointPath(a, 30));
  absl::StatusOr<field::FieldCheckpoint> fb = field::LoadFieldCheckpoint(FieldCheckpointPath(b, 30));
  absl::StatusOr<field::FieldCheckpoint> fc = field::LoadFieldCheckpoint(FieldCheckpointPath(c, 30));
  ASSERT_TRUE(fa.ok() && fb.ok() && fc.ok()) << fa.status() << fb.status() << fc.status();
  EXPECT_EQ(fa->adam.step, 18);
  EXPECT_EQ(fb->adam.step, 18);
  absl::StatusOr<field::DeformationField> init = field::DeformationField::Create(
      opt.field.config, fa->field.aabb(), fa->field.time_range(), opt.seed + opt.field.seed);
  ASSERT_TRUE(init.ok());
  auto relative = [&](const std::vector<float>& x, const std::vector<float>& y, const std::vector<float>& ref) {
    double diff = 0, scale = 0;
    for (size_t i = 0; i < x.size(); ++i) {
      diff += double(x[i] - y[i]) * (x[i] - y[i]);
      scale += double(x[i] - ref[i]) * (x[i] - ref[i]);
    }
    return std::sqrt(diff / std::max(scale, 1e-300));
  };
  const std::vector<float> zeros(fa->adam.m.size(), 0.0f);
  const double resumed = relative(fa->field.params(), fb->field.params(), init->params());
  const double host_vs_device = relative(fa->field.params(), fc->field.params(), init->params());
  const double m_resumed = relative(fa->adam.m, fb->adam.m, zeros);
  const double v_resumed = relative(fa->adam.v, fb->adam.v, zeros);
  std::fprintf(stderr, "device optimiser: resumed vs uninterrupted %.3g (m %.3g, v %.3g), host vs device %.3g\n",
               resumed, m_resumed, v_resumed, host_vs_device);
  EXPECT_NE(init->params(), fa->field.params());
  EXPECT_LT(resumed, 0.02);
  EXPECT_LT(m_resumed, 0.02);
  EXPECT_LT(v_resumed, 0.02);
  EXPECT_LT(host_vs_device, 0.02);
  // field.bin is the device's final field (read back at the end of the run).
  absl::StatusOr<field::DeformationField> written = field::LoadField(a + "/field.bin");
  ASSERT_TRUE(written.ok()) << written.status();
  EXPECT_EQ(written->params(), fa->field.params());
}

TEST(Trainer, FieldOptionsAreChecked) {
  const DriveLog log = ShortLog(8);
  TrainOptions opt = ShortOptions();
  opt.field = TinyField(30);  // not below the total
  EXPECT_EQ(Train(log, TempDir("bad"), opt).status().code(), absl::StatusCode::kInvalidArgument);
  opt.field = TinyField(-1);
  EXPECT_EQ(Train(log, TempDir("bad"), opt).status().code(), absl::StatusCode::kInvalidArgument);
  opt.field = TinyField(5);
  opt.field.config.channels = 0;
  EXPECT_FALSE(Train(log, TempDir("bad"), opt).ok());
}

// A run's written scene is never one just after an opacity reset (Hyper::min_iterations_after_reset):
// the reset that would fall within that many iterations of the end is skipped, while a stage that
// writes no outputs keeps its schedule.
float MaxOpacity(const TrainState& st) {
  float m = -1e9f;
  for (size_t i = 0; i < st.params.size(); ++i) m = std::max(m, st.params.opacity_logits[i]);
  return 1.0f / (1.0f + std::exp(-m));
}

TEST(Trainer, NoOpacityResetJustBeforeTheOutputs) {
  const DriveLog log = ShortLog(8);
  auto max_opacity = MaxOpacity;
  TrainOptions opt = ShortOptions();
  opt.iterations = 25;
  opt.hyper.min_iterations_after_reset = 10;
  opt.write_outputs = false;
  const std::string kept = TempDir("reset_kept");
  ASSERT_TRUE(Train(log, kept, opt).ok());
  absl::StatusOr<TrainState> a = LoadCheckpoint(kept + "/checkpoint.bin");
  ASSERT_TRUE(a.ok()) << a.status();
  EXPECT_LT(max_opacity(*a), 0.05f);  // reset at 20, five iterations to recover: still near 0.01
  opt.write_outputs = true;
  const std::string skipped = TempDir("reset_skipped");
  ASSERT_TRUE(Train(log, skipped, opt).ok());
  absl::StatusOr<TrainState> b = LoadCheckpoint(skipped + "/checkpoint.bin");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_GT(max_opacity(*b), 0.2f);  // from the init's 0.1, never reset
  // With room after it, the reset happens in a run that writes outputs too.
  opt.iterations = 35;
  const std::string room = TempDir("reset_room");
  ASSERT_TRUE(Train(log, room, opt).ok());
  absl::StatusOr<TrainState> c = LoadCheckpoint(room + "/checkpoint.bin");
  ASSERT_TRUE(c.ok()) << c.status();
  opt.write_outputs = false;
  const std::string room_no_outputs = TempDir("reset_room_no_outputs");
  ASSERT_TRUE(Train(log, room_no_outputs, opt).ok());
  absl::StatusOr<TrainState> d = LoadCheckpoint(room_no_outputs + "/checkpoint.bin");
  ASSERT_TRUE(d.ok()) << d.status();
  EXPECT_EQ(c->params.opacity_logits, d->params.opacity_logits);  // the same schedule, bit for bit (deterministic)
}

// Hyper::densify_until ends densification and the opacity resets: with it at 15 the run densifies
// at 10 only, so the Gaussians after 10 (a checkpoint of a killed run) are the ones after 30 and
// no reset at 20 pulls the opacities down; the spec's schedule densifies and resets at 20.
TEST(Trainer, DensifyUntilEndsDensificationAndResets) {
  const DriveLog log = ShortLog(8);
  TrainOptions opt = ShortOptions();
  const std::string full = TempDir("densify_full");
  ASSERT_TRUE(Train(log, full, opt).ok());
  absl::StatusOr<TrainState> spec = LoadCheckpoint(full + "/checkpoint.bin");
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->adam_step, 30 - 2);  // the densifications at 10 and 20 replace the tensors
  EXPECT_LT(MaxOpacity(*spec), 0.05f);

  opt.hyper.densify_until = 15;
  const std::string ended = TempDir("densify_ended");
  TrainOptions killed = opt;
  killed.stop_after = 15;
  ASSERT_TRUE(Train(log, ended, killed).ok());
  absl::StatusOr<TrainState> at10 = LoadCheckpoint(ended + "/checkpoint.bin");
  ASSERT_TRUE(at10.ok()) << at10.status();
  ASSERT_EQ(at10->iteration, 10);
  opt.resume = true;
  ASSERT_TRUE(Train(log, ended, opt).ok());
  absl::StatusOr<TrainState> at30 = LoadCheckpoint(ended + "/checkpoint.bin");
  ASSERT_TRUE(at30.ok()) << at30.status();
  EXPECT_EQ(at30->adam_step, 30 - 1);
  EXPECT_EQ(at30->size(), at10->size());
  EXPECT_NE(at30->size(), spec->size());  // the spec's densification at 20 changed the count
  EXPECT_GT(MaxOpacity(*at30), 0.2f);
}

// The bytes a fixed-seed deterministic run writes, pinned: a change of the trainer's structure
// (its parts, their order) that is meant to keep the behaviour must keep these. The concerns of an
// iteration take part: exposure, sky, depth, pose refinement, LiDAR supervision, densification and
// opacity reset, and in the second run the field (the preset-style optional motion prior is left
// out on these 8 frames, too few to track objects in: motion_prior_test holds it). Bit-identical
// for any thread count (docs/training.md "Reproducibility"); x86-64-v3, Debian's GCC 12. A change
// that is meant to change the numbers updates these digests and says so in its commit.
std::string FileDigest(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream bytes;
  bytes << in.rdbuf();
  const std::string b = bytes.str();
  char hex[17];
  std::snprintf(hex, sizeof(hex), "%016llx",
                static_cast<unsigned long long>(checked_file::Checksum(b.data(), b.size())));
  return hex;
}

TEST(Trainer, AFixedSeedRunKeepsItsBytes) {
  const DriveLog log = ShortLog(8);
  TrainOptions opt = ShortOptions();
  opt.pose_refinement = true;
  opt.hyper.pose_refine_from = 3;
  opt.write_outputs = true;
  const std::string still = TempDir("golden_static");
  ASSERT_TRUE(Train(log, still, opt).ok());
  EXPECT_EQ(FileDigest(still + "/checkpoint.bin"), "f7bf2bcb47150410");
  EXPECT_EQ(FileDigest(still + "/scene.ply"), "cd7ed3d695ae0cfb");

  opt.field = TinyField(12);
  opt.motion_prior.weight = 0.3;
  opt.motion_prior.optional = true;
  const std::string moving = TempDir("golden_field");
  ASSERT_TRUE(Train(log, moving, opt).ok());
  EXPECT_EQ(FileDigest(moving + "/checkpoint.bin"), "1b09697fce78786a");
  EXPECT_EQ(FileDigest(FieldCheckpointPath(moving, 30)), "dac7c0b1e8f4de35");
  EXPECT_EQ(FileDigest(moving + "/scene.ply"), "992ab29046a8f896");
}

TEST(Trainer, LearnsAndWritesOutputs) {
  const DriveLog log = ShortLog(8);
  const std::string dir = TempDir("out");
  TrainOptions opt = ShortOptions();
  opt.iterations = 60;
  opt.deterministic = false;
  opt.write_outputs = true;
  opt.exposure = false;
  opt.hyper = Hyper();  // the spec's schedule (no densification or reset within 60 iterations)
  absl::StatusOr<TrainResult> r = Train(log, dir, opt);
  ASSERT_TRUE(r.ok()) << r.status();
  absl::StatusOr<TrainState> st = LoadCheckpoint(dir + "/checkpoint.bin");
  ASSERT_TRUE(st.ok());
  // Curve entries (iteration, loss, psnr) every 10 iterations: the loss falls.
  ASSERT_GE(st->curve.size(), 6u * 3);
  EXPECT_LT(st->curve[st->curve.size() - 2], st->curve[1]);
  for (const char* f : {"scene.ply", "train_meta.json", "curve.png", "checkpoint.bin"}) {
    EXPECT_TRUE(std::filesystem::exists(dir + "/" + f)) << f;
  }
  EXPECT_TRUE(std::filesystem::exists(dir + "/preview"));
  EXPECT_EQ(r->heldout.frames.size(), 2u);  // frames 3 and 7
  EXPECT_GT(r->heldout.mean.psnr, 10.0);
}

}  // namespace
}  // namespace streetsim::train

namespace streetsim::train {
namespace {

// A KITTI raw drive with grayscale image_00 beside colour image_02 (the bundled clip's first 8
// frames, image_00 made from image_02's luminance at the same pose; only which views train how is
// checked here): the grayscale views are luminance-only by default, left out with kSkip, plain
// with kAsColour; a drive of grayscale cameras only trains them as they are.
TEST(Dataset, GrayscaleCamerasBesideColourOnes) {
  namespace fs = std::filesystem;
  const fs::path root = testing::ScratchDir("streetsim_dataset_gray", "kitti");
  const fs::path src = fs::path(kKitti), drive = root / "2011_09_26" / "2011_09_26_drive_sfnd_sync";
  fs::create_directories(drive / "image_00" / "data");
  fs::create_directories(drive / "image_02" / "data");
  fs::create_directories(drive / "velodyne_points" / "data");
  for (const char* f : {"calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt"}) {
    fs::copy_file(src.parent_path() / f, root / "2011_09_26" / f);
  }
  for (int i = 0; i < 8; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "%010d", i);
    const fs::path png = src / "image_02" / "data" / (std::string(name) + ".png");
    fs::copy_file(png, drive / "image_02" / "data" / png.filename());
    cv::Mat gray = cv::imread(png.string(), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(gray.empty());
    cv::imwrite((drive / "image_00" / "data" / png.filename()).string(), gray);
    fs::copy_file(src / "velodyne_points" / "data" / (std::string(name) + ".bin"),
                  drive / "velodyne_points" / "data" / (std::string(name) + ".bin"));
  }
  absl::StatusOr<DriveLog> log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  ASSERT_EQ(log->cameras.size(), 2u);
  DatasetOptions o;
  o.resolution_scale = 0.1;
  o.holdout_every = 0;
  o.load_depth = false;
  auto count = [&](GrayscaleCameras g, int* luminance) {
    o.grayscale = g;
    absl::StatusOr<std::vector<View>> v = LoadViews(*log, o);
    EXPECT_TRUE(v.ok()) << v.status();
    *luminance = 0;
    for (const View& view : *v) {
      *luminance += view.luminance_only;
      if (view.luminance_only) EXPECT_EQ(view.name.rfind("image_00/", 0), 0u) << view.name;
    }
    return static_cast<int>(v->size());
  };
  int luminance = 0;
  EXPECT_EQ(count(GrayscaleCameras::kLuminance, &luminance), 16);
  EXPECT_EQ(luminance, 8);
  EXPECT_EQ(count(GrayscaleCameras::kSkip, &luminance), 8);
  EXPECT_EQ(luminance, 0);
  EXPECT_EQ(count(GrayscaleCameras::kAsColour, &luminance), 16);
  EXPECT_EQ(luminance, 0);
  // Grayscale cameras only: as they are.
  fs::remove_all(drive / "image_02");
  log = OpenLog(drive.string());
  ASSERT_TRUE(log.ok()) << log.status();
  EXPECT_EQ(count(GrayscaleCameras::kLuminance, &luminance), 8);
  EXPECT_EQ(luminance, 0);
}

}  // namespace
}  // namespace streetsim::train
