// LiDAR sensor model and cpu range-image renderer (render/lidar/).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <sstream>
#include <string>

#include "gtest/gtest.h"
#include "render/lidar/lidar_model.h"
#include "render/lidar/lidar_renderer.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/lidar/lidar_test_scenes.h"
#include "scene/init/initial_scene.h"
#include "scene/log/open_log.h"

namespace streetsim {
namespace {

const std::string kData = STREETSIM_DATA_DIR;
const std::string kRaw = kData + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

using lidar_test::AddGaussian;
using lidar_test::SensorPose;

TEST(LidarModel, KittiTableAndCoordinates) {
  const LidarModel m = KittiHdl64e(2048);
  ASSERT_TRUE(m.Validate().ok()) << m.Validate();
  EXPECT_EQ(m.beams(), 64);
  EXPECT_NEAR(m.beam_elevation_deg.front(), 2.0, 0.5);
  EXPECT_NEAR(m.beam_elevation_deg.back(), -24.0, 1.0);
  for (int b = 0; b < m.beams(); ++b) EXPECT_NEAR(m.BeamCoordinate(m.BeamElevationRad(b)), b, 1e-9);
  // Between beams 10 and 11: linear in elevation; beyond the ends: extrapolated.
  const double mid = 0.5 * (m.BeamElevationRad(10) + m.BeamElevationRad(11));
  EXPECT_NEAR(m.BeamCoordinate(mid), 10.5, 1e-9);
  EXPECT_LT(m.BeamCoordinate(m.BeamElevationRad(0) + 0.01), 0);
  EXPECT_GT(m.BeamCoordinate(m.BeamElevationRad(63) - 0.01), 63);
  for (int c : {0, 1, 700, 1023, 1024, 2047}) EXPECT_NEAR(m.ColumnCoordinate(m.ColumnAzimuthRad(c)), c, 1e-6);
  // Straight ahead is between the two middle columns; left (+y) is left of the middle.
  EXPECT_NEAR(m.ColumnCoordinate(0.0), 1023.5, 1e-9);
  EXPECT_LT(m.ColumnCoordinate(0.5), 1023.5);
  EXPECT_EQ(m.ColumnTimeOffsetUs(0), 24);
  EXPECT_EQ(m.ColumnTimeOffsetUs(2047), 99'976);
  LidarModel bad = m;
  std::swap(bad.beam_elevation_deg[3], bad.beam_elevation_deg[4]);
  EXPECT_FALSE(bad.Validate().ok());
}

// The shipped table is what the estimator prints from the shared scans.
TEST(LidarModel, ShippedTableMatchesTheEstimate) {
  const std::string cmd = std::string(STREETSIM_BINARY_DIR) + "/tests/lidar/estimate_beam_table " + kRaw +
                          "/velodyne_points/data";
  FILE* p = popen(cmd.c_str(), "r");
  ASSERT_NE(p, nullptr);
  std::string text;
  char buf[4096];
  while (size_t got = fread(buf, 1, sizeof buf, p)) text.append(buf, got);
  ASSERT_EQ(pclose(p), 0) << text;
  const size_t brace = text.find('{');
  ASSERT_NE(brace, std::string::npos) << text;
  std::string nums = text.substr(brace + 1);
  std::replace(nums.begin(), nums.end(), ',', ' ');
  std::replace(nums.begin(), nums.end(), '}', ' ');
  std::istringstream in(nums);
  const LidarModel m = KittiHdl64e();
  double v;
  int b = 0;
  while (in >> v) {
    ASSERT_LT(b, 64);
    EXPECT_NEAR(v, m.beam_elevation_deg[b], 1e-9) << "beam " << b;
    ++b;
  }
  EXPECT_EQ(b, 64);
}

TEST(LidarRender, SingleGaussianReturnsItsRangeOnItsBeamAndColumn) {
  const LidarModel m = KittiHdl64e(2048);
  const int beam = 20, column = 700;
  const double range = 15.0;
  const Eigen::Isometry3d T_wl = SensorPose();
  GaussianStore s;
  AddGaussian(&s, T_wl * (m.RayDirection(beam, column) * range), Eigen::Vector3d::Constant(0.05), 0.95f);
  LidarRenderer renderer(2);
  LidarRenderOutput out;
  std::vector<float> refl = {0.8f};
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  opt.want_points = true;
  ASSERT_TRUE(renderer.Render(s, m, T_wl, opt, &out).ok());
  ASSERT_EQ(out.range.size(), 64u * 2048);
  const size_t pix = static_cast<size_t>(beam) * 2048 + column;
  const size_t argmax = std::max_element(out.alpha.begin(), out.alpha.end()) - out.alpha.begin();
  EXPECT_EQ(argmax, pix);
  EXPECT_NEAR(out.alpha[pix], 0.95, 1e-3);
  EXPECT_NEAR(out.range[pix], range, 1e-3);
  EXPECT_NEAR(out.intensity[pix], 0.8, 1e-5);
  // 5 cm at 15 m is 0.19 degrees: returns only on this pixel and its column neighbours.
  int returns = 0;
  for (size_t p = 0; p < out.range.size(); ++p) {
    if (out.range[p] > 0) {
      ++returns;
      EXPECT_EQ(p / 2048, static_cast<size_t>(beam));
      EXPECT_LE(std::abs(static_cast<int>(p % 2048) - column), 1);
    }
  }
  EXPECT_GE(returns, 1);
  ASSERT_EQ(out.points.size(), static_cast<size_t>(returns));
  for (size_t i = 0; i < out.points.size(); ++i) {
    if (out.points.column[i] == column) {
      EXPECT_LT((out.points.xyz[i].cast<double>() - m.RayDirection(beam, column) * range).norm(), 1e-3);
      EXPECT_EQ(out.points.time_us[i], m.ColumnTimeOffsetUs(column));
    }
  }
  // Behind the sensor (azimuth pi): drawn on both ends of the columns.
  GaussianStore back;
  AddGaussian(&back, T_wl * (Eigen::Vector3d(-10, 0, 0)), Eigen::Vector3d::Constant(0.05), 0.95f);
  ASSERT_TRUE(renderer.Render(back, m, T_wl, {}, &out).ok());
  const int row = static_cast<int>(std::lround(m.BeamCoordinate(0)));
  EXPECT_GT(out.alpha[row * 2048 + 0], 0.5);
  EXPECT_GT(out.alpha[row * 2048 + 2047], 0.5);
  EXPECT_NEAR(out.range[row * 2048 + 0], 10.0, 1e-3);
}

// The EWA footprint: a Gaussian of sigma s at range r spreads over s / r radians, i.e.
// s / r * columns / 2pi columns and s / r / (beam spacing) beams (+0.3 px^2 low-pass).
TEST(LidarRender, FootprintFollowsTheSphericalJacobian) {
  const LidarModel m = KittiHdl64e(2048);
  const int beam = 40, column = 1500;
  const double r = 20, sigma = 0.3;
  GaussianStore s;
  AddGaussian(&s, m.RayDirection(beam, column) * r, Eigen::Vector3d::Constant(sigma), 0.5f);
  LidarRenderer renderer(1);
  LidarRenderOutput out;
  ASSERT_TRUE(renderer.Render(s, m, Eigen::Isometry3d::Identity(), {}, &out).ok());
  // Along the row (elevation fixed): the horizontal distance is r cos(el).
  const double el = m.BeamElevationRad(beam);
  const double su = sigma / (r * std::cos(el)) * 2048 / (2 * M_PI);
  const double spacing_rad = (m.beam_elevation_deg[beam] - m.beam_elevation_deg[beam + 1]) * M_PI / 180;
  const double sv = sigma / r / spacing_rad;
  const double a0 = out.alpha[beam * 2048 + column];
  EXPECT_NEAR(a0, 0.5, 1e-4);
  for (int dc : {2, 4, 6}) {
    const double expect = std::exp(-0.5 * dc * dc / (su * su + 0.3));
    EXPECT_NEAR(out.alpha[beam * 2048 + column + dc] / a0, expect, 0.01) << dc;
    EXPECT_NEAR(out.alpha[beam * 2048 + column - dc] / a0, expect, 0.01) << dc;
  }
  const double expect_down = std::exp(-0.5 / (sv * sv + 0.3));
  EXPECT_NEAR(out.alpha[(beam + 1) * 2048 + column] / a0, expect_down, 0.02);
}

// A wall 10 m ahead (plane x = 10 in the sensor frame) of flat Gaussians: range 10 / (cos el cos az).
TEST(LidarRender, WallAtKnownDistance) {
  const LidarModel m = KittiHdl64e(2048);
  const Eigen::Isometry3d T_wl = SensorPose();
  GaussianStore s;
  const double spacing = 0.04;
  for (double y = -4; y <= 4; y += spacing)
    for (double z = -3; z <= 0.6; z += spacing)
      AddGaussian(&s, T_wl * Eigen::Vector3d(10, y, z), Eigen::Vector3d(0.005, spacing, spacing), 0.7f);
  LidarRenderer renderer(2);
  LidarRenderOutput out;
  ASSERT_TRUE(renderer.Render(s, m, T_wl, {}, &out).ok());
  double max_err = 0;
  std::vector<double> errs;
  int checked = 0;
  for (int b = 0; b < m.beams(); ++b) {
    for (int c = 0; c < m.columns; ++c) {
      const Eigen::Vector3d d = m.RayDirection(b, c);
      if (d.x() <= 0) continue;
      const Eigen::Vector3d hit = d * (10 / d.x());
      // Well inside the wall (its edges fade).
      if (std::abs(hit.y()) > 3.5 || hit.z() < -2.5 || hit.z() > 0.2) {
        continue;
      }
      const float r = out.range[static_cast<size_t>(b) * m.columns + c];
      ASSERT_GT(r, 0) << "beam " << b << " column " << c;
      max_err = std::max(max_err, std::abs(r - hit.norm()));
      errs.push_back(std::abs(r - hit.norm()));
      ++checked;
    }
  }
  std::sort(errs.begin(), errs.end());
  std::printf("wall: %d rays checked, |range error| median %.4f m, max %.4f m\n", checked,
              errs[errs.size() / 2], max_err);
  EXPECT_GT(checked, 3000);
  // Oblique rays (up to 20 degrees off the normal) are biased towards the nearer Gaussians of the
  // footprint, as the camera's expected depth is: a few cm at most.
  EXPECT_LT(errs[errs.size() / 2], 0.02);
  EXPECT_LT(max_err, 0.05);
  // Rays that miss the wall return nothing: beam 0 straight behind, the bottom beam far right.
  EXPECT_EQ(out.range[0], 0.0f);
  EXPECT_EQ(out.range[63 * 2048 + 1800], 0.0f);
}

// A dynamic scene's next time changes some Gaussians (serving): UpdateRows of just those gives the
// sweep a full Upload of the new store gives, bit for bit; a non-finite changed value drops the upload.
TEST(LidarRender, UpdateRowsRendersLikeUploadOfTheNewStore) {
  const LidarModel m = KittiHdl64e(512);
  const Eigen::Isometry3d T_wl = SensorPose();
  GaussianStore before;
  for (double y = -4; y <= 4; y += 0.1)
    for (double z = -3; z <= 0.6; z += 0.1)
      AddGaussian(&before, T_wl * Eigen::Vector3d(10, y, z), Eigen::Vector3d(0.005, 0.1, 0.1), 0.7f);
  GaussianStore after = before;
  std::vector<uint32_t> rows;
  for (uint32_t i = 0; i < before.size(); i += 3) {
    rows.push_back(i);
    after.means[i * 3] -= 1.5f;  // a third of the wall comes 1.5 m closer
  }
  ParamsChange change;
  change.rows = rows.data();
  change.num_rows = rows.size();
  change.means = true;
  LidarRenderer incremental(2), full(2);
  LidarRenderOutput a, b, c;
  ASSERT_TRUE(incremental.Upload(before).ok());
  ASSERT_TRUE(incremental.Render(m, T_wl, {}, &c).ok());
  ASSERT_TRUE(incremental.UpdateRows(after, change).ok());
  ASSERT_TRUE(incremental.Render(m, T_wl, {}, &a).ok());
  ASSERT_TRUE(full.Render(after, m, T_wl, {}, &b).ok());
  EXPECT_EQ(a.range, b.range);
  EXPECT_NE(a.range, c.range);
  after.means[rows[2] * 3 + 2] = std::nanf("");
  EXPECT_EQ(incremental.UpdateRows(after, change).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(incremental.Render(m, T_wl, {}, &a).ok()) << "a failed update leaves nothing to render";
  GaussianStore smaller = before;
  smaller.Resize(10);
  ASSERT_TRUE(incremental.Upload(before).ok());
  EXPECT_EQ(incremental.UpdateRows(smaller, change).code(), absl::StatusCode::kInvalidArgument);
}

// Rolling sweep: the sensor moves 1 m forward and yaws 3 degrees during the sweep between a wall
// 10 m ahead and one 10 m behind. Column c is measured from the pose at s = (c + 0.5) / columns of
// the way, so its range is the distance from that pose along its own ray (analytic; the pose
// computed here independently of lidar_sweep.cc). A static render would be off by up to ~0.5 m
// (behind: the sweep's start and end columns are 1 m apart).
TEST(LidarRender, RollingSweepRangesFollowEachColumnsPose) {
  const LidarModel m = KittiHdl64e(2048);
  GaussianStore s;
  const double spacing = 0.04;
  for (const double wall_x : {10.0, -10.0})
    for (double y = -6; y <= 6; y += spacing)
      for (double z = -3; z <= 0.6; z += spacing)
        AddGaussian(&s, Eigen::Vector3d(wall_x, y, z), Eigen::Vector3d(0.005, spacing, spacing), 0.7f);
  LidarRenderer renderer(2);
  ASSERT_TRUE(renderer.Upload(s).ok());
  // move_m, yaw: the sensor's motion over the sweep (0, 0: the static baseline of the same walls,
  // whose oblique rays lean ~2 cm towards the nearer Gaussians of their footprint, as in
  // WallAtKnownDistance). The moving sweep must be as good as that baseline.
  double base_median = 0, base_max = 0;
  for (const double move_m : {0.0, 1.0}) {
    const double yaw_total = move_m * 3 * M_PI / 180;
    LidarSweepPose sweep;
    sweep.T_world_from_lidar_end.translate(Eigen::Vector3d(move_m, 0, 0));
    sweep.T_world_from_lidar_end.rotate(Eigen::AngleAxisd(yaw_total, Eigen::Vector3d::UnitZ()));
    for (const auto kernel : {LidarRenderOptions::Kernel::kScalar, LidarRenderOptions::Kernel::kSimd}) {
      LidarRenderOptions opt;
      opt.kernel = kernel;
      LidarRenderOutput out;
      ASSERT_TRUE(renderer.Render(m, sweep, opt, &out).ok());
      std::vector<double> errs;
      double max_err = 0, max_static_err = 0, sum_signed = 0;
      for (int b = 0; b < m.beams(); ++b) {
        for (int c = 0; c < m.columns; ++c) {
          // The seam: a splat's copy one turn away keeps its own end's pose (docs/lidar.md).
          if (c < 16 || c >= m.columns - 16) continue;
          const double sc = (c + 0.5) / m.columns;
          const Eigen::Vector3d origin(sc * move_m, 0, 0);
          const Eigen::Vector3d d = Eigen::AngleAxisd(sc * yaw_total, Eigen::Vector3d::UnitZ()) * m.RayDirection(b, c);
          const double wall_x = d.x() > 0 ? 10.0 : -10.0;
          const double t = (wall_x - origin.x()) / d.x();
          const Eigen::Vector3d hit = origin + t * d;
          if (std::abs(hit.y()) > 5.5 || hit.z() < -2.5 || hit.z() > 0.2) continue;  // well inside a wall
          const float r = out.range[static_cast<size_t>(b) * m.columns + c];
          ASSERT_GT(r, 0) << "beam " << b << " column " << c;
          errs.push_back(std::abs(r - t));
          sum_signed += r - t;
          max_err = std::max(max_err, errs.back());
          // The range a static sensor at the sweep's start would measure along the same ray.
          const Eigen::Vector3d d0 = m.RayDirection(b, c);
          max_static_err = std::max(max_static_err, std::abs(r - wall_x / d0.x()));
        }
      }
      ASSERT_GT(errs.size(), 3000u);
      std::sort(errs.begin(), errs.end());
      std::printf("walls moving %.0f m (%s): %zu rays, |range error| median %.4f m, max %.4f m, mean signed %.4f m "
                  "(vs a static pose: max %.3f m)\n",
                  move_m, kernel == LidarRenderOptions::Kernel::kScalar ? "scalar" : "simd", errs.size(),
                  errs[errs.size() / 2], max_err, sum_signed / errs.size(), max_static_err);
      const double median = errs[errs.size() / 2];
      if (move_m == 0) {
        EXPECT_LT(median, 0.025);
        EXPECT_LT(max_err, 0.05);
        base_median = median;
        base_max = max_err;
      } else {
        EXPECT_LT(median, base_median + 0.003);
        EXPECT_LT(max_err, base_max + 0.015);
        EXPECT_GT(max_static_err, 0.5);  // the test would notice a static render
      }
    }
  }
}

// start == end is the static sweep, bit for bit; a sweep whose ends differ by 1 nm takes the
// rolling path (per-Gaussian pose columns, gathered poses) and must agree with it to float noise.
TEST(LidarRender, RollingSweepWithEqualEndsIsTheStaticRender) {
  SyntheticStreetOptions so;
  so.num_gaussians = 20'000;
  so.sh_degree = 0;
  const GaussianStore store = MakeSyntheticStreet(so);
  const LidarModel m = KittiHdl64e(1024);
  Eigen::Isometry3d T_wl = Eigen::Isometry3d::Identity();
  T_wl.translate(Eigen::Vector3d(20, 0.5, 1.73));
  T_wl.rotate(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()));
  LidarRenderer renderer(2);
  ASSERT_TRUE(renderer.Upload(store).ok());
  for (const auto kernel : {LidarRenderOptions::Kernel::kScalar, LidarRenderOptions::Kernel::kSimdAvx2,
                            LidarRenderOptions::Kernel::kSimd}) {
    LidarRenderOptions opt;
    opt.kernel = kernel;
    LidarRenderOutput fixed, equal, nearly;
    ASSERT_TRUE(renderer.Render(m, T_wl, opt, &fixed).ok());
    ASSERT_TRUE(renderer.Render(m, LidarSweepPose{T_wl, T_wl}, opt, &equal).ok());
    EXPECT_EQ(fixed.range, equal.range);
    EXPECT_EQ(fixed.alpha, equal.alpha);
    EXPECT_EQ(fixed.range_sum, equal.range_sum);
    Eigen::Isometry3d T_end = T_wl;
    T_end.translation().x() += 1e-9;
    ASSERT_TRUE(renderer.Render(m, LidarSweepPose{T_wl, T_end}, opt, &nearly).ok());
    EXPECT_EQ(nearly.num_visible, fixed.num_visible);
    double max_alpha = 0, max_range_sum = 0;
    for (size_t p = 0; p < fixed.alpha.size(); ++p) {
      max_alpha = std::max(max_alpha, static_cast<double>(std::abs(nearly.alpha[p] - fixed.alpha[p])));
      max_range_sum = std::max(max_range_sum, static_cast<double>(std::abs(nearly.range_sum[p] - fixed.range_sum[p])));
    }
    EXPECT_LT(max_alpha, 1e-4);
    EXPECT_LT(max_range_sum, 1e-3);
  }
}

TEST(LidarRender, SampledDropIsDeterministicAcrossThreadCounts) {
  const LidarModel m = KittiHdl64e(1024);
  GaussianStore s;
  for (int i = 0; i < 2000; ++i) {
    const double a = i * 0.0031, e = -0.3 + (i % 37) * 0.01;
    AddGaussian(&s, Eigen::Vector3d(8 * std::cos(a) * std::cos(e), 8 * std::sin(a) * std::cos(e), 8 * std::sin(e)),
                Eigen::Vector3d::Constant(0.08), 0.3f);
  }
  LidarRenderOptions opt;
  opt.sample_drop = true;
  opt.seed = 42;
  LidarRenderOutput a, b, c;
  LidarRenderer one(1), two(2);
  ASSERT_TRUE(one.Render(s, m, Eigen::Isometry3d::Identity(), opt, &a).ok());
  ASSERT_TRUE(two.Render(s, m, Eigen::Isometry3d::Identity(), opt, &b).ok());
  EXPECT_EQ(a.range, b.range);
  EXPECT_EQ(a.alpha, b.alpha);
  opt.seed = 43;
  ASSERT_TRUE(two.Render(s, m, Eigen::Isometry3d::Identity(), opt, &c).ok());
  EXPECT_NE(a.range, c.range);
  // Returns follow alpha: the fraction of partly covered rays that return is near their mean alpha.
  double sum_alpha = 0, returned = 0;
  for (size_t p = 0; p < a.alpha.size(); ++p) {
    if (a.alpha[p] > 0.05f && a.alpha[p] < 0.95f) {
      sum_alpha += a.alpha[p];
      returned += a.range[p] > 0;
    }
  }
  ASSERT_GT(sum_alpha, 100);
  EXPECT_NEAR(returned / sum_alpha, 1.0, 0.1);
}

TEST(LidarRender, RejectsBadInputs) {
  LidarRenderer r(1);
  LidarRenderOutput out;
  GaussianStore s;
  AddGaussian(&s, Eigen::Vector3d(5, 0, 0), Eigen::Vector3d::Constant(0.1), 0.5f);
  std::vector<float> refl(2, 0.5f);
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  EXPECT_EQ(r.Render(s, KittiHdl64e(), Eigen::Isometry3d::Identity(), opt, &out).code(),
            absl::StatusCode::kInvalidArgument);
  LidarModel m = KittiHdl64e();
  m.columns = 0;
  EXPECT_FALSE(r.Render(s, m, Eigen::Isometry3d::Identity(), {}, &out).ok());
  Eigen::Isometry3d bad = Eigen::Isometry3d::Identity();
  bad.linear() *= 2;
  EXPECT_FALSE(r.Render(s, KittiHdl64e(), bad, {}, &out).ok());
  EXPECT_FALSE(r.Render(s, KittiHdl64e(), LidarSweepPose{Eigen::Isometry3d::Identity(), bad}, {}, &out).ok());
  Eigen::Isometry3d nan_end = Eigen::Isometry3d::Identity();
  nan_end.translation().x() = std::nan("");
  EXPECT_EQ(r.Render(s, KittiHdl64e(), LidarSweepPose{Eigen::Isometry3d::Identity(), nan_end}, {}, &out).code(),
            absl::StatusCode::kInvalidArgument);
  // Nothing uploaded; a store that fails Validate() (caught at upload, not per sweep).
  LidarRenderer fresh(1);
  EXPECT_EQ(fresh.Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).code(),
            absl::StatusCode::kInvalidArgument);
  GaussianStore nan = s;
  nan.means[0] = std::nanf("");
  EXPECT_FALSE(fresh.Upload(nan).ok());
  EXPECT_FALSE(fresh.Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).ok());
  ASSERT_TRUE(fresh.Upload(s).ok());
  EXPECT_TRUE(fresh.Render(KittiHdl64e(), Eigen::Isometry3d::Identity(), {}, &out).ok());
}

// The vectorised kernels (LidarRenderOptions::Kernel::kSimd, the default) against the scalar
// reference on a street scene, with reflectance and a pose off the axes (the seam behind the sensor
// crosses the scene): range image, alpha, intensity and the unnormalised sums agree within float
// tolerance. The two differ only in rounding (inline exp / polynomial atan2 / float beam map vs
// libm and double; the blend evaluates whole 16-lane rows where the reference visits the opacity
// box), so a handful of rays whose alpha sits on a threshold may differ; the bulk must be tight.
TEST(LidarRender, SimdKernelsMatchTheScalarReference) {
  const GaussianStore& store = lidar_test::StreetBackward().store;  // the shared 60k street
  const std::vector<float>& refl = lidar_test::StreetBackward().refl;
  const LidarModel m = KittiHdl64e(2048);
  Eigen::Isometry3d T_wl = Eigen::Isometry3d::Identity();
  T_wl.translate(Eigen::Vector3d(20, 0.5, 1.73));
  T_wl.rotate(Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitZ()));
  T_wl.rotate(Eigen::AngleAxisd(0.02, Eigen::Vector3d::UnitX()));
  LidarRenderer renderer(2);
  ASSERT_TRUE(renderer.Upload(store).ok());
  EXPECT_EQ(renderer.uploaded_size(), store.size());
  LidarRenderOptions opt;
  opt.reflectance = &refl;
  LidarRenderOutput simd, ref;
  opt.kernel = LidarRenderOptions::Kernel::kScalar;
  ASSERT_TRUE(renderer.Render(m, T_wl, opt, &ref).ok());
  for (const LidarRenderOptions::Kernel kernel : {LidarRenderOptions::Kernel::kSimdAvx2, LidarRenderOptions::Kernel::kSimd}) {
    const char* isa = kernel == LidarRenderOptions::Kernel::kSimd ? LidarRenderer::SimdIsa() : "avx2";
    opt.kernel = kernel;
    ASSERT_TRUE(renderer.Render(m, T_wl, opt, &simd).ok());
    // Same culls and tile boxes: the splat and tile-instance counts agree to a few splats.
    EXPECT_NEAR(static_cast<double>(simd.num_visible), static_cast<double>(ref.num_visible),
                1e-4 * ref.num_visible + 2);
    EXPECT_NEAR(static_cast<double>(simd.num_tile_instances), static_cast<double>(ref.num_tile_instances),
                1e-4 * ref.num_tile_instances + 2);
    ASSERT_EQ(simd.range.size(), ref.range.size());
    const size_t P = ref.range.size();
    size_t returns = 0, return_mismatch = 0, alpha_off = 0, range_off = 0, intensity_off = 0;
    double max_alpha = 0, max_range_rel = 0, max_intensity = 0;
    std::vector<double> alpha_err, range_err;
    for (size_t p = 0; p < P; ++p) {
      const double da = std::abs(simd.alpha[p] - ref.alpha[p]);
      alpha_err.push_back(da);
      max_alpha = std::max(max_alpha, da);
      alpha_off += da > 1e-3;
      const double ds = std::abs(simd.range_sum[p] - ref.range_sum[p]);
      range_off += ds > 1e-3 * std::max(1.0, static_cast<double>(ref.range_sum[p]));
      const double di = std::abs(simd.intensity_sum[p] - ref.intensity_sum[p]);
      intensity_off += di > 1e-3;
      if ((simd.range[p] > 0) != (ref.range[p] > 0)) {
        ++return_mismatch;
        continue;
      }
      if (ref.range[p] > 0) {
        ++returns;
        const double rel = std::abs(simd.range[p] - ref.range[p]) / ref.range[p];
        range_err.push_back(rel);
        max_range_rel = std::max(max_range_rel, rel);
        max_intensity = std::max(max_intensity, static_cast<double>(std::abs(simd.intensity[p] - ref.intensity[p])));
      }
  }
  std::sort(alpha_err.begin(), alpha_err.end());
  std::sort(range_err.begin(), range_err.end());
  std::printf("simd vs scalar (%s): %zu splats (ref %zu), %zu returns; |d alpha| p99.9 %.2e max %.2e; "
              "|d range|/range p99.9 %.2e max %.2e; |d intensity| max %.2e; off (alpha, range_sum, "
              "intensity_sum): %zu %zu %zu; return mismatches %zu\n",
              isa, simd.num_visible, ref.num_visible, returns,
              alpha_err[alpha_err.size() * 999 / 1000], max_alpha, range_err[range_err.size() * 999 / 1000],
              max_range_rel, max_intensity, alpha_off, range_off, intensity_off, return_mismatch);
  EXPECT_GT(returns, P / 2);
  EXPECT_LT(alpha_err[alpha_err.size() * 999 / 1000], 1e-4);
  EXPECT_LT(range_err[range_err.size() * 999 / 1000], 1e-4);
  // Threshold flips and rounding at the opacity-box edge: at most 0.1 % of the rays.
  EXPECT_LE(alpha_off, P / 1000);
  EXPECT_LE(range_off, P / 1000);
  EXPECT_LE(intensity_off, P / 1000);
  EXPECT_LE(return_mismatch, P / 1000);
  }
  // Rendering again gives the same image (no state leaks between sweeps).
  LidarRenderOutput again;
  ASSERT_TRUE(renderer.Render(m, T_wl, opt, &again).ok());
  EXPECT_EQ(again.range, simd.range);
  EXPECT_EQ(again.alpha, simd.alpha);
  // The one-shot overload (upload + render) gives the same image too.
  ASSERT_TRUE(renderer.Render(store, m, T_wl, opt, &again).ok());
  EXPECT_EQ(again.range, simd.range);
}

// The LiDAR init scene of the KITTI clip (every other frame) rendered from a held-out frame's
// LiDAR pose against that frame's real scan binned into the same range image.
TEST(LidarRender, KittiInitSceneMatchesAHeldOutScan) {
  absl::StatusOr<DriveLog> log = OpenLog(kRaw);
  ASSERT_TRUE(log.ok()) << log.status();
  ASSERT_FALSE(log->lidars.empty());
  InitOptions init;
  init.frames.first = 0;
  init.frames.last = 40;
  init.frames.stride = 2;
  init.drop_dynamic = true;  // moving vehicles would smear along their paths
  InitStats stats;
  absl::StatusOr<GaussianStore> scene = BuildInitialScene(*log, init, &stats);
  ASSERT_TRUE(scene.ok()) << scene.status();
  const int k = 21;  // held out (odd)
  const Frame& frame = log->frames[k];
  ASSERT_FALSE(frame.lidars.empty());
  LidarModel m = KittiHdl64e(2048);
  m.T_ego_from_lidar = log->lidars[0].T_ego_from_lidar;
  const Eigen::Isometry3d T_wl = frame.T_world_from_ego * m.T_ego_from_lidar;
  absl::StatusOr<LidarScan> scan = LoadLidarScan(frame.lidars[0].path);
  ASSERT_TRUE(scan.ok()) << scan.status();
  std::vector<float> real;
  BinPointsToRangeImage(m, scan->points, nullptr, &real);

  LidarRenderer renderer;
  LidarRenderOutput out;
  ASSERT_TRUE(renderer.Render(*scene, m, T_wl, {}, &out).ok());
  // All rays where both return, and those within the left camera's horizontal field of view
  // (+-40 degrees about the sensor's x axis), the only part of the scene the init keeps (it keeps
  // LiDAR points some camera saw, so outside that cone rays pass through to far structure).
  std::vector<double> err, err_fov;
  size_t rendered = 0, real_returns = 0;
  for (size_t p = 0; p < real.size(); ++p) {
    rendered += out.range[p] > 0;
    real_returns += real[p] > 0;
    if (out.range[p] > 0 && real[p] > 0) {
      const double e = std::abs(out.range[p] - real[p]);
      err.push_back(e);
      const double az = m.ColumnAzimuthRad(static_cast<int>(p % m.columns));
      if (std::abs(az) < 40 * M_PI / 180) err_fov.push_back(e);
    }
  }
  ASSERT_GT(err.size(), 1000u);
  ASSERT_GT(err_fov.size(), 1000u);
  auto quantile = [](std::vector<double> v, double q) {
    std::sort(v.begin(), v.end());
    return v[static_cast<size_t>(q * (v.size() - 1))];
  };
  size_t real_fov = 0, rendered_fov = 0;
  for (size_t p = 0; p < real.size(); ++p) {
    if (std::abs(m.ColumnAzimuthRad(static_cast<int>(p % m.columns))) >= 40 * M_PI / 180) continue;
    real_fov += real[p] > 0;
    rendered_fov += out.range[p] > 0;
  }
  std::printf("KITTI frame %d: %zu Gaussians (%zu splats), %.1f ms\n"
              "  all rays: real returns %zu, rendered %zu, both %zu; |range error| median %.3f m, p90 %.3f m\n"
              "  camera fov (|az| < 40 deg): real %zu, rendered %zu, both %zu; |range error| median %.3f m, "
              "p75 %.3f m, p90 %.3f m\n",
              k, scene->size(), out.num_visible, out.total_ms, real_returns, rendered, err.size(),
              quantile(err, 0.5), quantile(err, 0.9), real_fov, rendered_fov, err_fov.size(),
              quantile(err_fov, 0.5), quantile(err_fov, 0.75), quantile(err_fov, 0.9));
  // Measured 0.51 m (all) and 0.70 m (fov). Most of it is the init scene, not the renderer: its
  // isotropic Gaussians (nearest-neighbour scale, median 0.13 m: ~0.75 degrees, 2-3 beams, at
  // 10 m) and opacity 0.1 bleed across depth edges, so rays passing just above a near object take
  // part of its range (a frame's own scan alone gives 0.46 m; docs/lidar.md). Regression bounds:
  EXPECT_LT(quantile(err, 0.5), 0.6);
  EXPECT_LT(quantile(err_fov, 0.5), 0.8);
}

}  // namespace
}  // namespace streetsim
