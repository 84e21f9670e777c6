// The vulkan LiDAR renderer (render/vulkan/lidar_renderer_vk.h) against the cpu scalar reference
// (LidarRenderOptions::Kernel::kScalar): the same rules, so alpha, the sums and the range image
// agree within float tolerance (the projection uses float beam tables and a polynomial atan2, the
// reference double and libm), with at most a handful of rays flipping a threshold. Runs on Mesa
// lavapipe when no GPU is present; fails (not skips) when no Vulkan device can be created.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <opencv2/imgcodecs.hpp>

#include "gtest/gtest.h"
#include "tests/common/scratch_dir.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "render/lidar/lidar_sweep.h"
#include "render/vulkan/lidar_renderer_vk.h"
#include "scene/gaussians/ply_io.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/lidar/lidar_test_scenes.h"

namespace streetsim {
namespace {

// One renderer for the whole binary: device and pipeline creation dominate a small test.
VulkanLidarRenderer& Vk() {
  static VulkanLidarRenderer* renderer = [] {
    auto created = VulkanLidarRenderer::Create(VulkanDevicePreference::kLavapipe);
    if (!created.ok()) {
      ADD_FAILURE() << "no vulkan LiDAR renderer: " << created.status();
      return static_cast<VulkanLidarRenderer*>(nullptr);
    }
    std::printf("%s\n", (*created)->device_name().c_str());
    return created->release();
  }();
  if (renderer == nullptr) std::abort();
  return *renderer;
}

using lidar_test::AddGaussian;
using lidar_test::SensorPose;

// Gaussians all around the sensor (the seam behind it included): ranges 3..60 m, elevations
// -30..+8 degrees (some above and below the beams), anisotropic, rotated, opacity 0.05..0.95.
GaussianStore RandomScene(const Eigen::Isometry3d& T_wl, int n, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> U(0, 1);
  GaussianStore s;
  for (int i = 0; i < n; ++i) {
    const double az = (U(rng) * 2 - 1) * M_PI, el = (-30 + 38 * U(rng)) * M_PI / 180;
    const double r = 3 + 57 * U(rng) * U(rng);
    const Eigen::Vector3d p(r * std::cos(el) * std::cos(az), r * std::cos(el) * std::sin(az), r * std::sin(el));
    const Eigen::Vector3d scale(0.02 + 0.4 * U(rng) * U(rng), 0.02 + 0.15 * U(rng), 0.01 + 0.1 * U(rng));
    Eigen::Quaterniond q(U(rng) - 0.5, U(rng) - 0.5, U(rng) - 0.5, U(rng) - 0.5);
    q.normalize();
    AddGaussian(&s, T_wl * p, scale, static_cast<float>(0.05 + 0.9 * U(rng)), q);
  }
  return s;
}

uint64_t SplitMix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

struct Agreement {
  double alpha_p999 = 0, alpha_max = 0, range_rel_p999 = 0, range_rel_max = 0;
  size_t returns = 0, alpha_off = 0, range_sum_off = 0, intensity_sum_off = 0, return_mismatch = 0;
};

// Compares a vulkan output with the reference ray by ray and checks the agreement contract: the
// 99.9th percentile of |d alpha| and of |d range| / range below p999 (1e-4), at most 0.1 % of the
// rays off by more than 1e-3 (threshold flips), the same splat and tile-instance counts to a few.
Agreement ExpectAgreement(const LidarRenderOutput& vk, const LidarRenderOutput& ref, const char* what,
                          double p999 = 1e-4) {
  Agreement a;
  EXPECT_EQ(vk.beams, ref.beams);
  EXPECT_EQ(vk.columns, ref.columns);
  const size_t P = ref.alpha.size();
  EXPECT_EQ(vk.alpha.size(), P);
  EXPECT_EQ(vk.range.size(), P);
  if (vk.alpha.size() != P || vk.range.size() != P) return a;
  EXPECT_NEAR(static_cast<double>(vk.num_visible), static_cast<double>(ref.num_visible), 1e-4 * ref.num_visible + 2)
      << what;
  EXPECT_NEAR(static_cast<double>(vk.num_tile_instances), static_cast<double>(ref.num_tile_instances),
              1e-4 * ref.num_tile_instances + 2)
      << what;
  std::vector<double> alpha_err, range_err;
  for (size_t p = 0; p < P; ++p) {
    const double da = std::abs(vk.alpha[p] - ref.alpha[p]);
    alpha_err.push_back(da);
    a.alpha_max = std::max(a.alpha_max, da);
    a.alpha_off += da > 1e-3;
    a.range_sum_off += std::abs(vk.range_sum[p] - ref.range_sum[p]) > 1e-3 * std::max(1.0f, ref.range_sum[p]);
    a.intensity_sum_off += std::abs(vk.intensity_sum[p] - ref.intensity_sum[p]) > 1e-3;
    if ((vk.range[p] > 0) != (ref.range[p] > 0)) {
      ++a.return_mismatch;
      continue;
    }
    if (ref.range[p] > 0) {
      ++a.returns;
      const double rel = std::abs(vk.range[p] - ref.range[p]) / ref.range[p];
      range_err.push_back(rel);
      a.range_rel_max = std::max(a.range_rel_max, rel);
    }
  }
  std::sort(alpha_err.begin(), alpha_err.end());
  std::sort(range_err.begin(), range_err.end());
  a.alpha_p999 = alpha_err[alpha_err.size() * 999 / 1000];
  a.range_rel_p999 = range_err.empty() ? 0 : range_err[range_err.size() * 999 / 1000];
  std::printf("%s: %zu splats (ref %zu), %zu tile instances (ref %zu), %zu returns; |d alpha| p99.9 %.2e max "
              "%.2e; |d range|/range p99.9 %.2e max %.2e; off (alpha, range_sum, intensity_sum): %zu %zu %zu; "
              "return mismatches %zu\n",
              what, vk.num_visible, ref.num_visible, vk.num_tile_instances, ref.num_tile_instances, a.returns,
              a.alpha_p999, a.alpha_max, a.range_rel_p999, a.range_rel_max, a.alpha_off, a.range_sum_off,
              a.intensity_sum_off, a.return_mismatch);
  EXPECT_LT(a.alpha_p999, p999) << what;
  EXPECT_LT(a.range_rel_p999, p999) << what;
  EXPECT_LE(a.alpha_off, P / 1000) << what;
  EXPECT_LE(a.range_sum_off, P / 1000) << what;
  EXPECT_LE(a.intensity_sum_off, P / 1000) << what;
  EXPECT_LE(a.return_mismatch, P / 1000) << what;
  return a;
}

LidarRenderOutput RenderCpu(const GaussianStore& store, const LidarModel& m, const LidarSweepPose& sweep,
                            LidarRenderOptions opt) {
  LidarRenderer cpu(2);
  opt.kernel = LidarRenderOptions::Kernel::kScalar;
  LidarRenderOutput out;
  const absl::Status s = cpu.Render(store, m, sweep, opt, &out);
  EXPECT_TRUE(s.ok()) << s;
  return out;
}

TEST(VulkanLidar, SingleGaussianAndTheSeamBehindTheSensor) {
  const LidarModel m = KittiHdl64e(2048);
  const int beam = 20, column = 700;
  const Eigen::Isometry3d T_wl = SensorPose();
  GaussianStore s;
  AddGaussian(&s, T_wl * (m.RayDirection(beam, column) * 15.0), Eigen::Vector3d::Constant(0.05), 0.95f);
  std::vector<float> refl = {0.8f};
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  opt.want_points = true;
  opt.sweep_start_us = 1000;
  LidarRenderOutput out;
  ASSERT_TRUE(Vk().Render(s, m, T_wl, opt, &out).ok());
  EXPECT_EQ(Vk().uploaded_size(), 1u);
  ASSERT_EQ(out.range.size(), 64u * 2048);
  const size_t pix = static_cast<size_t>(beam) * 2048 + column;
  EXPECT_EQ(static_cast<size_t>(std::max_element(out.alpha.begin(), out.alpha.end()) - out.alpha.begin()), pix);
  EXPECT_NEAR(out.alpha[pix], 0.95, 1e-3);
  EXPECT_NEAR(out.range[pix], 15.0, 1e-3);
  EXPECT_NEAR(out.intensity[pix], 0.8, 1e-5);
  EXPECT_NEAR(out.range_sum[pix], 15.0 * out.alpha[pix], 1e-3);
  ASSERT_GE(out.points.size(), 1u);
  for (size_t i = 0; i < out.points.size(); ++i) {
    EXPECT_EQ(out.points.beam[i], beam);
    EXPECT_EQ(out.points.time_us[i], 1000 + m.ColumnTimeOffsetUs(out.points.column[i]));
  }
  ExpectAgreement(out, RenderCpu(s, m, LidarSweepPose::Static(T_wl), opt), "single Gaussian");

  // Straight behind the sensor (azimuth pi, the seam): drawn on both ends of the columns, once
  // as the splat and once as its copy one turn away; a wide one near the seam on one side too.
  GaussianStore back;
  AddGaussian(&back, T_wl * Eigen::Vector3d(-10, 0, 0), Eigen::Vector3d::Constant(0.05), 0.95f);
  AddGaussian(&back, T_wl * Eigen::Vector3d(-12, -0.4, -1), Eigen::Vector3d(0.1, 0.6, 0.1), 0.7f);
  ASSERT_TRUE(Vk().Render(back, m, T_wl, {}, &out).ok());
  const int row = static_cast<int>(std::lround(m.BeamCoordinate(0)));
  EXPECT_GT(out.alpha[row * 2048 + 0], 0.5);
  EXPECT_GT(out.alpha[row * 2048 + 2047], 0.5);
  EXPECT_NEAR(out.range[row * 2048 + 0], 10.0, 1e-3);
  EXPECT_NEAR(out.range[row * 2048 + 2047], 10.0, 1e-3);
  EXPECT_EQ(out.num_visible, 4u);  // two splats, each with its seam copy
  ExpectAgreement(out, RenderCpu(back, m, LidarSweepPose::Static(T_wl), {}), "seam");
}

TEST(VulkanLidar, MatchesTheScalarReferenceOnARandomScene) {
  const LidarModel m = KittiHdl64e(2048);
  const Eigen::Isometry3d T_wl = SensorPose();
  const GaussianStore store = RandomScene(T_wl, 8'000, 7);
  std::vector<float> refl(store.size());
  for (size_t i = 0; i < refl.size(); ++i) refl[i] = static_cast<float>((i * 53) % 97) / 96.0f;
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  opt.return_alpha_threshold = 0.3f;
  ASSERT_TRUE(Vk().Upload(store).ok());
  LidarRenderOutput vk;
  ASSERT_TRUE(Vk().Render(m, T_wl, opt, &vk).ok());
  const LidarRenderOutput ref = RenderCpu(store, m, LidarSweepPose::Static(T_wl), opt);
  // Steep, overlapping, anisotropic splats: the cpu's own vectorised kernel (the same float beam
  // map and atan2) is 8e-5 from the reference at the 99.9th percentile of |d range| / range here.
  const Agreement a = ExpectAgreement(vk, ref, "random scene", 2e-4);
  EXPECT_GT(a.returns, ref.range.size() / 4);

  // Sampled drop: the cpu's hash, so where alpha agrees the decisions agree. A decision may only
  // differ where the ray's uniform draw lies between the two alphas.
  opt.sample_drop = true;
  opt.seed = 0x123456789abcdefull;
  ASSERT_TRUE(Vk().Render(m, T_wl, opt, &vk).ok());
  const LidarRenderOutput ref_drop = RenderCpu(store, m, LidarSweepPose::Static(T_wl), opt);
  size_t returns = 0, unexplained = 0, flips = 0;
  for (size_t p = 0; p < vk.range.size(); ++p) {
    const bool rv = vk.range[p] > 0, rc = ref_drop.range[p] > 0;
    returns += rv;
    if (rv == rc) continue;
    ++flips;
    const uint64_t h = SplitMix64(opt.seed ^ SplitMix64(p + 1));
    const float u = static_cast<float>((h >> 40) * (1.0 / 16777216.0));
    const float lo = std::min(vk.alpha[p], ref_drop.alpha[p]), hi = std::max(vk.alpha[p], ref_drop.alpha[p]);
    unexplained += !(u >= lo && u < hi);
  }
  std::printf("sampled drop: %zu returns, %zu decisions differ, %zu not explained by alpha\n", returns, flips,
              unexplained);
  EXPECT_GT(returns, vk.range.size() / 10);
  EXPECT_EQ(unexplained, 0u);
  EXPECT_LE(flips, vk.range.size() / 1000);
  // Drops follow the seed.
  LidarRenderOutput other;
  opt.seed += 1;
  ASSERT_TRUE(Vk().Render(m, T_wl, opt, &other).ok());
  EXPECT_NE(other.range, vk.range);
}

// Image sizes that are not multiples of the 16 x 16 tile (partial tiles on both axes, the seam
// inside a partial tile), a model of 37 beams, and degenerate Gaussians that the culls must treat
// as the reference does (at the sensor, straight up, huge and tiny scales, extreme opacities).
TEST(VulkanLidar, MatchesTheScalarReferenceWithOddSizes) {
  LidarModel m = KittiHdl64e(1001);
  m.beam_elevation_deg.resize(37);
  m.min_range_m = 1.0;
  const Eigen::Isometry3d T_wl = SensorPose();
  GaussianStore store = RandomScene(T_wl, 4'000, 11);
  AddGaussian(&store, T_wl * Eigen::Vector3d(0, 0, 0), Eigen::Vector3d::Constant(0.1), 0.9f);
  AddGaussian(&store, T_wl * Eigen::Vector3d(0, 0, 10), Eigen::Vector3d::Constant(0.1), 0.9f);
  AddGaussian(&store, T_wl * Eigen::Vector3d(10, 1, 0), Eigen::Vector3d::Constant(1e12), 0.9f);
  AddGaussian(&store, T_wl * Eigen::Vector3d(10, -1, 0), Eigen::Vector3d::Constant(1e-12), 0.9f);
  AddGaussian(&store, T_wl * Eigen::Vector3d(11, 0, -1), Eigen::Vector3d::Constant(0.2), 0.5f);
  store.opacity_logits.back() = 80.0f;
  AddGaussian(&store, T_wl * Eigen::Vector3d(12, 0, -1), Eigen::Vector3d::Constant(0.2), 0.5f);
  store.opacity_logits.back() = -80.0f;
  ASSERT_TRUE(store.Validate().ok()) << store.Validate();
  ASSERT_TRUE(Vk().Upload(store).ok());
  LidarRenderOutput vk;
  ASSERT_TRUE(Vk().Render(m, T_wl, {}, &vk).ok());
  ASSERT_EQ(vk.range.size(), 37u * 1001);
  const LidarRenderOutput ref = RenderCpu(store, m, LidarSweepPose::Static(T_wl), {});
  const Agreement a = ExpectAgreement(vk, ref, "odd sizes", 2e-4);
  EXPECT_GT(a.returns, ref.range.size() / 4);
  // The last column and the last beam are rendered (not left at zero by a partial tile).
  size_t last_column = 0, last_beam = 0;
  for (int b = 0; b < 37; ++b) last_column += vk.alpha[b * 1001 + 1000] > 0;
  for (int c = 0; c < 1001; ++c) last_beam += vk.alpha[36 * 1001 + c] > 0;
  EXPECT_GT(last_column, 0u);
  EXPECT_GT(last_beam, 0u);
}

TEST(VulkanLidar, MatchesTheScalarReferenceOnAStreet) {
  const GaussianStore& store = lidar_test::StreetBackward().store;  // the shared 60k street
  const std::vector<float>& refl = lidar_test::StreetBackward().refl;
  const LidarModel m = KittiHdl64e(2048);
  Eigen::Isometry3d T_wl = Eigen::Isometry3d::Identity();
  T_wl.translate(Eigen::Vector3d(20, 0.5, 1.73));
  T_wl.rotate(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()));
  T_wl.rotate(Eigen::AngleAxisd(0.02, Eigen::Vector3d::UnitX()));
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  ASSERT_TRUE(Vk().Upload(store).ok());
  LidarRenderOutput vk, again;
  ASSERT_TRUE(Vk().Render(m, T_wl, opt, &vk).ok());
  const Agreement a = ExpectAgreement(vk, RenderCpu(store, m, LidarSweepPose::Static(T_wl), opt), "street");
  EXPECT_GT(a.returns, vk.range.size() / 2);
  // Deterministic: the same sweep again gives the same image, bit for bit.
  ASSERT_TRUE(Vk().Render(m, T_wl, opt, &again).ok());
  EXPECT_EQ(again.alpha, vk.alpha);
  EXPECT_EQ(again.range, vk.range);
  EXPECT_EQ(again.intensity_sum, vk.intensity_sum);
}

// Rolling sweep: start == end is the static render exactly; a moving, turning sensor agrees with the
// cpu's rolling render and differs from either end's static render.
TEST(VulkanLidar, RollingSweep) {
  SyntheticStreetOptions so;
  so.num_gaussians = 30'000;
  so.sh_degree = 0;
  const GaussianStore store = MakeSyntheticStreet(so);
  const LidarModel m = KittiHdl64e(1024);
  Eigen::Isometry3d start = Eigen::Isometry3d::Identity();
  start.translate(Eigen::Vector3d(20, 0.5, 1.73));
  start.rotate(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitZ()));
  Eigen::Isometry3d end = start;
  end.pretranslate(Eigen::Vector3d(2.0, 0.3, 0.0));  // 20 m/s for 100 ms
  end.rotate(Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()));
  ASSERT_TRUE(Vk().Upload(store).ok());
  LidarRenderOutput fixed, same, rolling;
  ASSERT_TRUE(Vk().Render(m, start, {}, &fixed).ok());
  ASSERT_TRUE(Vk().Render(m, LidarSweepPose{start, start}, {}, &same).ok());
  EXPECT_EQ(same.alpha, fixed.alpha);
  EXPECT_EQ(same.range, fixed.range);
  ASSERT_TRUE(Vk().Render(m, LidarSweepPose{start, end}, {}, &rolling).ok());
  ExpectAgreement(rolling, RenderCpu(store, m, LidarSweepPose{start, end}, {}), "rolling");
  size_t differ = 0;
  for (size_t p = 0; p < rolling.range.size(); ++p) differ += std::abs(rolling.range[p] - fixed.range[p]) > 0.05f;
  std::printf("rolling vs static at the start pose: %zu of %zu rays differ by > 5 cm\n", differ, rolling.range.size());
  EXPECT_GT(differ, rolling.range.size() / 20);
}

// The capacity estimates of a fresh renderer (tile instances: max(2 per Gaussian, 16k); sorted
// splats: max(1.125 per Gaussian, 1024)) are exceeded by wide splats that all cross the seam (two
// entries each, ~10 tiles per entry): the sweep is recorded again with room for all, with the
// reference's result.
TEST(VulkanLidar, GrowsItsBuffersWhenTheEstimatesAreExceeded) {
  auto fresh = VulkanLidarRenderer::Create();
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  const LidarModel m = KittiHdl64e(512);
  GaussianStore s;
  for (int i = 0; i < 2000; ++i) {
    const double el = (-20 + 0.01 * i) * M_PI / 180;
    AddGaussian(&s, Eigen::Vector3d(-8 * std::cos(el), 0.001 * (i - 1000), 8 * std::sin(el)),
                Eigen::Vector3d(0.1, 1.0, 0.5), 0.4f);
  }
  LidarRenderOutput out;
  ASSERT_TRUE((*fresh)->Render(s, m, Eigen::Isometry3d::Identity(), {}, &out).ok());
  EXPECT_EQ(out.num_visible, 4000u);
  EXPECT_GT(out.num_tile_instances, 16384u);
  EXPECT_EQ((*fresh)->rerenders(), 1);
  ExpectAgreement(out, RenderCpu(s, m, LidarSweepPose::Static(Eigen::Isometry3d::Identity()), {}), "grown");
  // The grown buffers are kept: the next sweep fits.
  ASSERT_TRUE((*fresh)->Render(m, Eigen::Isometry3d::Identity(), {}, &out).ok());
  EXPECT_EQ((*fresh)->rerenders(), 1);
}

TEST(VulkanLidar, RejectsBadInputs) {
  auto fresh = VulkanLidarRenderer::Create();
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  LidarRenderOutput out;
  // Nothing uploaded.
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).code(),
            absl::StatusCode::kInvalidArgument);
  GaussianStore s;
  AddGaussian(&s, Eigen::Vector3d(5, 0, 0), Eigen::Vector3d::Constant(0.1), 0.5f);
  // A store failing validation is caught at upload and leaves nothing uploaded.
  GaussianStore nan = s;
  nan.means[0] = std::nanf("");
  EXPECT_FALSE((*fresh)->Upload(nan).ok());
  EXPECT_EQ((*fresh)->uploaded_size(), 0u);
  EXPECT_FALSE((*fresh)->Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).ok());
  ASSERT_TRUE((*fresh)->Upload(s).ok());
  // Invalid model, non-rigid or non-finite poses (start and end), reflectance of the wrong size.
  LidarModel bad_model = KittiHdl64e();
  bad_model.columns = 0;
  EXPECT_EQ((*fresh)->Render(bad_model, Eigen::Isometry3d::Identity(), {}, &out).code(),
            absl::StatusCode::kInvalidArgument);
  bad_model = KittiHdl64e();
  std::swap(bad_model.beam_elevation_deg[3], bad_model.beam_elevation_deg[4]);
  EXPECT_FALSE((*fresh)->Render(bad_model, Eigen::Isometry3d::Identity(), {}, &out).ok());
  Eigen::Isometry3d scaled = Eigen::Isometry3d::Identity();
  scaled.linear() *= 2;
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), scaled, {}, &out).code(), absl::StatusCode::kInvalidArgument);
  Eigen::Isometry3d inf = Eigen::Isometry3d::Identity();
  inf.translation().x() = std::numeric_limits<double>::infinity();
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), inf, {}, &out).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), LidarSweepPose{Eigen::Isometry3d::Identity(), inf}, {}, &out).code(),
            absl::StatusCode::kInvalidArgument);
  std::vector<float> refl(2, 0.5f);
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), opt, &out).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*fresh)->Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, nullptr).code(),
            absl::StatusCode::kInvalidArgument);
  // Still usable after the errors; an empty scene renders no returns.
  ASSERT_TRUE((*fresh)->Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).ok());
  EXPECT_GT(*std::max_element(out.alpha.begin(), out.alpha.end()), 0.3f);
  ASSERT_TRUE((*fresh)->Render(GaussianStore{}, KittiHdl64e(256), Eigen::Isometry3d::Identity(), {}, &out).ok());
  EXPECT_EQ(out.range.size(), 64u * 256);
  EXPECT_EQ(*std::max_element(out.alpha.begin(), out.alpha.end()), 0.0f);
  EXPECT_EQ(out.num_visible, 0u);
}

// streetsim render --lidar --backend vulkan end to end: the same range image as the cpu backend
// (within float tolerance), and the PLY of points.
TEST(VulkanLidar, CliRendersWithTheVulkanBackend) {
  const std::string bin = std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim";
  const std::string dir = testing::ScratchDir("vulkan_lidar", "cli");
  GaussianStore s;
  for (double y = -4; y <= 8; y += 0.05) {
    for (double z = 0; z <= 4; z += 0.05) AddGaussian(&s, Eigen::Vector3d(17, y, z), Eigen::Vector3d(0.005, 0.05, 0.05), 0.73f);
  }
  ASSERT_TRUE(WriteGaussianPly(s, dir + "/wall.ply").ok());
  std::ofstream(dir + "/pose.json") << R"({"T_world_from_lidar": [1,0,0,5, 0,1,0,2, 0,0,1,1.7, 0,0,0,1]})";
  auto run = [&](const std::string& backend, const std::string& tag) {
    const std::string cmd = bin + " render --lidar --backend " + backend + " --ply " + dir + "/wall.ply --pose " +
                            dir + "/pose.json --out-range " + dir + "/" + tag + ".tiff --out-points " + dir + "/" +
                            tag + ".ply 2> " + dir + "/" + tag + ".txt";
    const int rc = std::system(cmd.c_str());
    std::ifstream f(dir + "/" + tag + ".txt");
    std::printf("%s", std::string((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>()).c_str());
    return WEXITSTATUS(rc);
  };
  ASSERT_EQ(run("vulkan", "vk"), 0);
  ASSERT_EQ(run("cpu", "cpu"), 0);
  const cv::Mat vk = cv::imread(dir + "/vk.tiff", cv::IMREAD_UNCHANGED);
  const cv::Mat cpu = cv::imread(dir + "/cpu.tiff", cv::IMREAD_UNCHANGED);
  ASSERT_EQ(vk.type(), CV_32FC1);
  ASSERT_EQ(vk.rows, 64);
  ASSERT_EQ(vk.cols, 2048);
  ASSERT_EQ(cpu.size(), vk.size());
  const LidarModel m = KittiHdl64e(2048);
  EXPECT_NEAR(vk.at<float>(10, 1023), 12.0 / m.RayDirection(10, 1023).x(), 0.02);
  EXPECT_EQ(vk.at<float>(10, 0), 0.0f);
  int returns = 0, mismatches = 0;
  for (int r = 0; r < vk.rows; ++r) {
    for (int c = 0; c < vk.cols; ++c) {
      const float a = vk.at<float>(r, c), b = cpu.at<float>(r, c);
      returns += a > 0;
      mismatches += (a > 0) != (b > 0) || std::abs(a - b) > 1e-3f * b;
    }
  }
  EXPECT_GT(returns, 2000);
  EXPECT_LE(mismatches, 5);
  EXPECT_TRUE(std::filesystem::exists(dir + "/vk.ply"));
  // Bad arguments are still exit 2 with --backend vulkan.
  EXPECT_EQ(std::system((bin + " render --lidar --backend vulkan --ply " + dir + "/missing.ply --pose " + dir +
                         "/pose.json --out-range " + dir + "/x.tiff 2> /dev/null")
                            .c_str()) >> 8,
            2);
}

}  // namespace
}  // namespace streetsim
