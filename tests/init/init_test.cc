// Initial scenes: depth maps, dynamic masks, scales, and the whole init rendered from a logged
// camera against its image.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "gtest/gtest.h"
#include "render/cpu/cpu_engine.h"
#include "scene/init/depth_maps.h"
#include "scene/init/dynamic_mask.h"
#include "scene/init/initial_scene.h"
#include "scene/init/knn_scales.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/init/triangulated_points.h"
#include "scene/init/voxel_grid.h"
#include "scene/log/kdtree.h"
#include "scene/log/open_log.h"

namespace streetsim {
namespace {

const std::string kData = STREETSIM_DATA_DIR;
const std::string kRaw = kData + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

const DriveLog& RawLog() {
  static const DriveLog* log = [] {
    absl::StatusOr<DriveLog> l = OpenLog(kRaw);
    if (!l.ok()) std::abort();
    return new DriveLog(*std::move(l));
  }();
  return *log;
}

// Over all pixels, or only where mask (alpha) > 0.5.
double Psnr(const std::vector<float>& rgb, const cv::Mat& image, const std::vector<float>* mask = nullptr) {
  double se = 0;
  size_t n = 0;
  for (int v = 0; v < image.rows; ++v) {
    for (int u = 0; u < image.cols; ++u) {
      if (mask && (*mask)[static_cast<size_t>(v) * image.cols + u] <= 0.5f) continue;
      ++n;
      const cv::Vec3b px = image.at<cv::Vec3b>(v, u);
      for (int c = 0; c < 3; ++c) {
        const double d = std::clamp(rgb[(static_cast<size_t>(v) * image.cols + u) * 3 + c], 0.0f, 1.0f) - px[c] / 255.0;
        se += d * d;
      }
    }
  }
  return 10 * std::log10(1.0 / (se / (3.0 * n)));
}

TEST(DepthMaps, NearestWins) {
  CameraIntrinsics k;
  k.width = 64;
  k.height = 48;
  k.fx = k.fy = 50;
  k.cx = 31.5;
  k.cy = 23.5;
  // Three points on one ray (far first, so order does not decide) and one on another.
  k.cx = 31.2;
  k.cy = 23.2;
  const std::vector<Eigen::Vector3f> pts = {{2, 1, 10}, {1, 0.5f, 5}, {1.4f, 0.7f, 7}, {0, 0, 3}, {0, 0, 0.2f}};
  const cv::Mat d = ProjectDepth(pts, Eigen::Isometry3d::Identity(), k);
  EXPECT_FLOAT_EQ(d.at<float>(28, 41), 5.0f);  // (41.2, 28.2): the 5 m point hides 7 m and 10 m
  EXPECT_FLOAT_EQ(d.at<float>(23, 31), 3.0f);  // 0.2 m is nearer than the 0.5 m minimum
  EXPECT_EQ(cv::countNonZero(d), 2);
}

TEST(DepthMaps, KittiFrameHasDenseValidDepthWhereTheLidarLooks) {
  absl::StatusOr<cv::Mat> d = SparseDepthMap(RawLog(), 0, 0);
  ASSERT_TRUE(d.ok()) << d.status();
  EXPECT_EQ(d->cols, 1242);
  const int valid = cv::countNonZero(*d);
  double lo, hi;
  cv::minMaxLoc(*d, &lo, &hi, nullptr, nullptr, *d > 0);
  std::printf("depth map frame 0: %d valid pixels, %.2f..%.2f m\n", valid, lo, hi);
  EXPECT_GT(valid, 10'000);
  EXPECT_GE(lo, 0.5);
  EXPECT_LT(hi, 130);
  // The HDL-64 looks no higher than +2 degrees: the top rows of the image hold no returns near.
  EXPECT_EQ(cv::countNonZero((*d)(cv::Rect(0, 0, 1242, 20)) > 0), 0);
}

TEST(KnnScales, RegularGridGivesItsSpacing) {
  std::vector<Eigen::Vector3f> pts;
  for (int i = 0; i < 20; ++i) for (int j = 0; j < 20; ++j) pts.emplace_back(0.1f * i, 0.1f * j, 0);
  const std::vector<float> s = KnnLogScales(pts);
  EXPECT_NEAR(std::exp(s[10 * 20 + 10]), 0.1, 1e-4);  // interior: 4 neighbours at exactly 0.1 m
}

TEST(VoxelGrid, AveragesWithinAVoxel) {
  VoxelGrid grid(1.0);
  grid.Add({0.2, 0.2, 0.2}, 0.1f);
  grid.Add({0.4, 0.6, 0.8}, 0.3f);
  grid.Add({1.5, 0.5, 0.5}, 1.0f);
  std::vector<Eigen::Vector3f> p;
  std::vector<float> r;
  grid.Extract(1, &p, &r);
  ASSERT_EQ(p.size(), 2u);
  EXPECT_TRUE(p[0].isApprox(Eigen::Vector3f(0.3f, 0.4f, 0.5f)));
  EXPECT_FLOAT_EQ(r[0], 0.2f);
  grid.Extract(2, &p, &r);
  EXPECT_EQ(p.size(), 1u);
}

// A static street (ground, walls on both sides) with a car that moves 2.5 m between scans, seen by
// a sensor that itself moves 1 m per neighbour (the mask must compensate the ego motion).
TEST(DynamicMask, FlagsTheMovingCarNotTheStreet) {
  const auto street = [](double car_x, std::vector<Eigen::Vector3f>* s, std::vector<Eigen::Vector3f>* car) {
    for (double x = -30; x <= 30; x += 0.1) {
      for (double y = -10; y <= 10; y += 0.1) s->emplace_back(x, y, -1.7);
      for (double z = -1.7; z <= 3; z += 0.1) {
        s->emplace_back(x, 10, z);
        s->emplace_back(x, -10, z);
      }
    }
    for (double x = 0; x <= 4.5; x += 0.1) for (double z = -1.5; z <= 0; z += 0.1) car->emplace_back(car_x + x, -4, z);
  };
  std::vector<Eigen::Vector3f> scan, car;
  street(0, &scan, &car);
  const size_t car_begin = scan.size();
  scan.insert(scan.end(), car.begin(), car.end());
  std::vector<NeighbourScan> neighbours;
  for (double step : {-1.0, 1.0}) {
    std::vector<Eigen::Vector3f> s, c;
    street(2.5 * step, &s, &c);
    s.insert(s.end(), c.begin(), c.end());
    NeighbourScan nb;
    nb.T_scan_from_neighbour.translation() << step, 0, 0;
    for (const Eigen::Vector3f& p : s) nb.points.push_back(p - Eigen::Vector3f(step, 0, 0));
    neighbours.push_back(std::move(nb));
  }
  const DynamicMask mask = DynamicMaskFromScans(scan, neighbours, {});
  size_t car_flagged = 0, static_flagged = 0, static_judged = 0;
  for (size_t i = 0; i < scan.size(); ++i) {
    if (i >= car_begin) {
      car_flagged += mask.dynamic[i];
    } else if (mask.judged[i]) {
      ++static_judged;
      static_flagged += mask.dynamic[i];
    }
  }
  const double car_fraction = double(car_flagged) / (scan.size() - car_begin);
  std::printf("synthetic street: car %.0f%% flagged, static %zu of %zu flagged\n", 100 * car_fraction,
              static_flagged, static_judged);
  EXPECT_GT(car_fraction, 0.5);
  EXPECT_EQ(static_flagged, 0u);
  EXPECT_GT(static_judged, 10000u);
}

// The shared clip: the tanker truck passing in the right lane (LiDAR box x -8..15 m, y -5..-1.5 m,
// z -1.2..2.5 m) against the road surface within 20 m (z < -1.5 m).
TEST(DynamicMask, KittiTankerIsFlaggedFarMoreThanTheRoad) {
  for (int f : {20, 40, 60}) {
    absl::StatusOr<DynamicMask> mask = ComputeDynamicMask(RawLog(), f);
    ASSERT_TRUE(mask.ok()) << mask.status();
    absl::StatusOr<LidarScan> scan = LoadLidarScan(RawLog().frames[f].lidars[0].path);
    ASSERT_TRUE(scan.ok());
    ASSERT_EQ(mask->dynamic.size(), scan->points.size());
    size_t road = 0, road_dyn = 0, lane = 0, lane_dyn = 0;
    for (size_t i = 0; i < scan->points.size(); ++i) {
      const Eigen::Vector3f& p = scan->points[i];
      if (!mask->judged[i]) continue;
      if (p.z() < -1.5f && p.head<2>().norm() < 20) {
        ++road;
        road_dyn += mask->dynamic[i];
      }
      if (p.x() > -8 && p.x() < 15 && p.y() > -5 && p.y() < -1.5f && p.z() > -1.2f && p.z() < 2.5f) {
        ++lane;
        lane_dyn += mask->dynamic[i];
      }
    }
    const double road_fraction = double(road_dyn) / road, lane_fraction = double(lane_dyn) / lane;
    std::printf("frame %d: right lane (tanker) %.1f%% of %zu flagged, road %.3f%% of %zu\n", f,
                100 * lane_fraction, lane, 100 * road_fraction, road);
    EXPECT_GT(lane_fraction, 0.15);
    EXPECT_LT(road_fraction, 0.01);
  }
}

// The initial scene of frames 0-39, rendered by the cpu engine from logged camera 2 at frame 20,
// against the image: far above a blank (black) image.
TEST(InitialScene, RenderFromALoggedCameraLooksLikeTheImage) {
  const DriveLog& log = RawLog();
  InitOptions options;
  options.frames = {0, 40, 1};
  options.voxel_m = 0.1;
  options.sky = true;
  InitStats stats;
  absl::StatusOr<GaussianStore> store = BuildInitialScene(log, options, &stats);
  ASSERT_TRUE(store.ok()) << store.status();
  ASSERT_TRUE(store->Validate().ok());
  EXPECT_EQ(stats.source, "lidar");
  EXPECT_EQ(stats.gaussians, stats.seen + stats.sky_points);
  EXPECT_GT(stats.gaussians, 50'000u);
  EXPECT_NEAR(1 / (1 + std::exp(-store->opacity_logits[0])), 0.1, 1e-6);

  const Frame& frame = log.frames[20];
  const CameraIntrinsics& k = log.cameras[0].intrinsics;
  PinholeCamera camera;
  camera.width = k.width;
  camera.height = k.height;
  camera.fx = k.fx;
  camera.fy = k.fy;
  camera.cx = k.cx;
  camera.cy = k.cy;
  camera.T_world_from_cam = WorldFromCamera(log, frame, frame.cameras[0]);
  std::unique_ptr<Engine> engine = CreateCpuEngine();
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = engine->Upload(*store);
  ASSERT_TRUE(scene.ok()) << scene.status();
  RenderOutput out;
  ASSERT_TRUE(engine->Render(**scene, camera, {}, &out).ok());
  absl::StatusOr<cv::Mat> image = LoadImageRgb(frame.cameras[0].path);
  ASSERT_TRUE(image.ok());
  const double psnr = Psnr(out.rgb, *image);
  const double blank = Psnr(std::vector<float>(out.rgb.size(), 0.0f), *image);
  cv::Scalar mean = cv::mean(*image);
  std::vector<float> grey(out.rgb.size());
  for (size_t i = 0; i < grey.size(); ++i) grey[i] = static_cast<float>(mean[i % 3] / 255.0);
  const double flat = Psnr(grey, *image);
  const double psnr_covered = Psnr(out.rgb, *image, &out.alpha);
  const double blank_covered = Psnr(std::vector<float>(out.rgb.size(), 0.0f), *image, &out.alpha);
  const double flat_covered = Psnr(grey, *image, &out.alpha);
  size_t covered = 0;
  for (float a : out.alpha) covered += a > 0.5f;
  std::printf("init: %zu Gaussians (%zu LiDAR, %zu sky) from %zu voxels (%zu raw LiDAR points, %d frames) in "
              "%.1f s, median scale %.3f m\nPSNR at frame 20, whole image: init %.2f dB, black %.2f dB, "
              "mean colour %.2f dB; where alpha > 0.5 (%.0f%% of pixels): init %.2f, black %.2f, mean colour %.2f\n",
              stats.gaussians, stats.seen, stats.sky_points, stats.voxels, stats.lidar_points_raw, stats.frames_used,
              stats.seconds, stats.median_scale_m, psnr, blank, flat, 100.0 * covered / out.alpha.size(),
              psnr_covered, blank_covered, flat_covered);
  EXPECT_GT(psnr, blank + 4);
  EXPECT_GT(psnr, flat + 1);
  EXPECT_GT(psnr_covered, blank_covered + 4);
}

TEST(InitialScene, CameraOnlyLogsUseColmapPointsOrTriangulatedPoints) {
  absl::StatusOr<DriveLog> colmap = OpenLog(kData + "/colmap_plush");
  ASSERT_TRUE(colmap.ok());
  InitStats stats;
  absl::StatusOr<GaussianStore> store = BuildInitialScene(*colmap, {}, &stats);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ(stats.source, "colmap_points");
  EXPECT_EQ(store->size(), 25784u);

  absl::StatusOr<DriveLog> odometry = OpenLog(kData + "/kitti_odometry_excerpt/seq_a");
  ASSERT_TRUE(odometry.ok());
  InitOptions options;
  options.random_points = 5000;
  options.frames = {0, 10, 1};
  store = BuildInitialScene(*odometry, options, &stats);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ(stats.source, "triangulated");
  EXPECT_GT(store->size(), 1000u);
  ASSERT_EQ(stats.notes.size(), 1u);
  EXPECT_NE(stats.notes[0].find("points triangulated with the log's poses"), std::string::npos) << stats.notes[0];
}

TEST(TriangulateMidpoint, RaysThroughAPointMeetThereAndParallelRaysDoNot) {
  const Eigen::Vector3d p(1.5, -2.0, 7.0), a(0, 0, 0), b(0.8, 0.1, -0.3);
  Eigen::Vector3d got;
  ASSERT_TRUE(TriangulateMidpoint(a, (p - a).normalized(), b, (p - b) * 3.0, &got));
  EXPECT_LT((got - p).norm(), 1e-9);
  // Skew rays: the midpoint of their closest approach.
  ASSERT_TRUE(TriangulateMidpoint({0, 0, 0}, {1, 0, 0}, {0, 1, 2}, {0, 0, 1}, &got));
  EXPECT_LT((got - Eigen::Vector3d(0, 0.5, 0)).norm(), 1e-9);
  EXPECT_FALSE(TriangulateMidpoint(a, {0, 0, 1}, b, {0, 0, 2}, &got));
}

// A street of two textured surfaces (a wall 12 m ahead, a road 1.6 m below the camera), each
// pixel the colour of 0.25 m tiles of random grey where its ray first meets one, seen by one camera
// driving forward (and a little sideways) or by a camera that never moves.
struct SyntheticStreet {
  static constexpr double kWallZ = 12, kRoadY = 1.6;
  DriveLog log;
  std::string dir;

  static double Depth(const Eigen::Vector3d& origin, const Eigen::Vector3d& dir, Eigen::Vector3d* hit) {
    double t = (kWallZ - origin.z()) / dir.z();
    if (dir.y() > 0) t = std::min(t, (kRoadY - origin.y()) / dir.y());
    *hit = origin + t * dir;
    return t;
  }
  static uint8_t Tile(const Eigen::Vector3d& p) {
    const int64_t a = static_cast<int64_t>(std::floor(p.x() / 0.25)), b = static_cast<int64_t>(std::floor(p.y() / 0.25)),
                  c = static_cast<int64_t>(std::floor(p.z() / 0.25));
    uint64_t h = static_cast<uint64_t>(a) * 73856093u ^ static_cast<uint64_t>(b) * 19349669u ^
                 static_cast<uint64_t>(c) * 83492791u;
    h ^= h >> 13;
    h *= 0x9E3779B97F4A7C15ull;
    return static_cast<uint8_t>(40 + (h >> 56) % 180);
  }

  SyntheticStreet(const std::string& name, double step_m) {
    dir = (std::filesystem::temp_directory_path() / ("streetsim_tri_" + name)).string();
    std::filesystem::create_directories(dir);
    CameraSensor cam;
    cam.name = "synthetic";
    cam.colour = false;
    cam.intrinsics.width = 640;
    cam.intrinsics.height = 360;
    cam.intrinsics.fx = cam.intrinsics.fy = 500;
    cam.intrinsics.cx = 319.5;
    cam.intrinsics.cy = 179.5;
    log.cameras.push_back(cam);
    for (int f = 0; f < 4; ++f) {
      Frame frame;
      frame.source_index = f;
      frame.time_us = f * 100'000;
      frame.T_world_from_ego.translation() = Eigen::Vector3d(0.1 * f * step_m, 0, f * step_m);
      cv::Mat image(360, 640, CV_8UC1);
      for (int v = 0; v < 360; ++v) {
        for (int u = 0; u < 640; ++u) {
          Eigen::Vector3d hit;
          Depth(frame.T_world_from_ego.translation(), Eigen::Vector3d((u - 319.5) / 500, (v - 179.5) / 500, 1), &hit);
          image.at<uint8_t>(v, u) = Tile(hit);
        }
      }
      const std::string path = dir + "/" + std::to_string(f) + ".png";
      cv::imwrite(path, image);
      frame.cameras.push_back({0, frame.time_us, path});
      log.frames.push_back(frame);
    }
  }
  ~SyntheticStreet() { std::filesystem::remove_all(dir); }
};

// Triangulated with the poses the images were made with, the points lie on the street's surfaces:
// a sign, frame or intrinsics mistake would put them elsewhere.
TEST(TriangulatedPoints, PointsOfASyntheticStreetLieOnItsSurfaces) {
  SyntheticStreet street("moving", 1.0);
  TriangulationOptions options;
  absl::StatusOr<TriangulatedPoints> found = TriangulateWithKnownPoses(street.log, options);
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(found->image_pairs, 3 + 2);  // gaps 1 and 2 over 4 frames
  ASSERT_GT(found->points.size(), 500u) << found->matches << " matches";
  std::vector<double> rel;  // relative distance to the surface along the first camera's ray
  for (const Eigen::Vector3f& p : found->points) {
    const Eigen::Vector3d x = p.cast<double>();
    Eigen::Vector3d hit;
    SyntheticStreet::Depth(Eigen::Vector3d::Zero(), x.normalized(), &hit);
    rel.push_back(std::abs(x.norm() - hit.norm()) / hit.norm());
  }
  std::sort(rel.begin(), rel.end());
  std::printf("%zu points (%zu of %zu matches): relative distance to the surface median %.4f, p90 %.4f\n",
              found->points.size(), found->triangulated, found->matches, rel[rel.size() / 2], rel[rel.size() * 9 / 10]);
  // ORB's corners are a pixel or so off at coarse pyramid levels, and rays meeting at 1-3 degrees
  // turn that into a few percent of depth (measured: median 3 %, p90 11 %); a wrong scale, axis or
  // sign is tens of percent.
  EXPECT_LT(rel[rel.size() / 2], 0.05);
  EXPECT_LT(rel[rel.size() * 9 / 10], 0.2);
  // Images are detected and pairs matched on all cores; the points merge in pair order, so a
  // second run gives the same points in the same order.
  absl::StatusOr<TriangulatedPoints> again = TriangulateWithKnownPoses(street.log, options);
  ASSERT_TRUE(again.ok());
  ASSERT_EQ(again->points.size(), found->points.size());
  for (size_t i = 0; i < found->points.size(); ++i) ASSERT_EQ(again->points[i], found->points[i]) << i;
  // Grey on grey: colours are the tiles' (equal channels in [0.15, 0.87]).
  for (const Eigen::Vector3f& c : found->rgb) {
    EXPECT_NEAR(c[0], c[1], 1e-6);
    EXPECT_GE(c[0], 0.1f);
    EXPECT_LE(c[0], 0.9f);
  }

  // The same images with the camera claimed to stand still: no parallax, so nothing triangulates
  // and the initial scene is random points in the frusta, as the note says.
  DriveLog standing = street.log;
  for (Frame& f : standing.frames) f.T_world_from_ego = Eigen::Isometry3d::Identity();
  found = TriangulateWithKnownPoses(standing, options);
  ASSERT_TRUE(found.ok()) << found.status();
  EXPECT_EQ(found->points.size(), 0u);
  InitOptions init;
  init.random_points = 400;
  InitStats stats;
  absl::StatusOr<GaussianStore> store = BuildInitialScene(standing, init, &stats);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ(stats.source, "random_frusta");
  EXPECT_EQ(store->size(), 400u);
  ASSERT_EQ(stats.notes.size(), 1u);
  EXPECT_NE(stats.notes[0].find("too few"), std::string::npos) << stats.notes[0];
}

}  // namespace
}  // namespace streetsim
