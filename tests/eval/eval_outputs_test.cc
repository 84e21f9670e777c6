// Eval outputs (scene/eval/decomposition.h, eval_video.h): the static/dynamic split and its
// renders on a synthetic moving band, a static scene's decomposition, and the eval video read
// back with OpenCV.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <random>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/videoio.hpp>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/field/static_skip.h"
#include "scene/eval/decomposition.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/eval_video.h"
#include "tests/field/field_test_util.h"
#include "tests/train/band_scene.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;
using testing::BandField;
using testing::BandScene;
using testing::CpuEngine;
using testing::kC0;
using testing::TopCamera;

std::string TestDir(const std::string& name) {
  const fs::path d = fs::path(::testing::TempDir()) / ("streetsim_eval_outputs_" + std::to_string(getpid()) + "_" + name);
  fs::remove_all(d);
  fs::create_directories(d);
  return d.string();
}

TEST(Decomposition, SplitIsTheServersAnalysisAndCountsAddUp) {
  const field::DeformationField f = BandField();
  const GaussianStore g = BandScene(30, 60);
  ThreadPool pool(2);
  absl::StatusOr<StaticDynamicSplit> split = SplitStaticDynamic(&f, g, pool);
  ASSERT_TRUE(split.ok()) << split.status();
  EXPECT_TRUE(split->has_field);
  absl::StatusOr<field::StaticAnalysis> a = field::AnalyseStatic(f, g, field::StaticSkipOptions{}, pool);
  ASSERT_TRUE(a.ok());
  EXPECT_EQ(split->dynamic_rows, a->dynamic_rows);
  EXPECT_EQ(split->static_rows.size() + split->dynamic_rows.size(), g.size());
  std::vector<int> seen(g.size(), 0);
  for (uint32_t r : split->static_rows) ++seen[r];
  for (uint32_t r : split->dynamic_rows) ++seen[r];
  EXPECT_TRUE(std::all_of(seen.begin(), seen.end(), [](int s) { return s == 1; }));
  EXPECT_TRUE(std::is_sorted(split->static_rows.begin(), split->static_rows.end()));
  // The band moves, the far Gaussians do not.
  for (uint32_t r : split->dynamic_rows) EXPECT_LT(r, 30u) << "far Gaussian " << r << " called dynamic";
  EXPECT_GT(split->dynamic_rows.size(), 20u);

  absl::StatusOr<StaticDynamicSplit> none = SplitStaticDynamic(nullptr, g, pool);
  ASSERT_TRUE(none.ok());
  EXPECT_FALSE(none->has_field);
  EXPECT_EQ(none->static_rows.size(), g.size());
  EXPECT_TRUE(none->dynamic_rows.empty());
}

TEST(Decomposition, SelectRowsKeepsEveryParameter) {
  const GaussianStore g = BandScene(3, 4);
  const GaussianStore s = SelectRows(g, {5, 1});
  ASSERT_EQ(s.size(), 2u);
  EXPECT_EQ(s.sh_degree, 3);
  EXPECT_TRUE(s.Validate().ok());
  EXPECT_EQ(s.means[3], g.means[3]);
  EXPECT_EQ(s.means[0], g.means[15]);
  EXPECT_EQ(s.sh[48 + 2], g.sh[48 + 2]);
  EXPECT_EQ(s.opacity_logits[0], g.opacity_logits[5]);
  const GaussianStore all = SelectRows(g, {0, 1, 2, 3, 4, 5, 6});
  EXPECT_EQ(all.means, g.means);
  EXPECT_EQ(all.sh, g.sh);
  EXPECT_EQ(SelectRows(g, {}).size(), 0u);
}

TEST(Decomposition, DynamicRenderIsEmptyWhereNoDynamicGaussianProjects) {
  auto field = std::make_shared<const field::DeformationField>(BandField());
  const GaussianStore g = BandScene(30, 60);
  std::unique_ptr<Engine> engine = CpuEngine();
  const Eigen::Vector3f background(0.2f, 0.3f, 0.5f);
  absl::StatusOr<std::unique_ptr<Decomposer>> d = Decomposer::Create(*engine, g, field, background);
  ASSERT_TRUE(d.ok()) << d.status();
  const StaticDynamicSplit& split = (*d)->split();
  ASSERT_FALSE(split.dynamic_rows.empty());
  const PinholeCamera cam = TopCamera();
  const int W = cam.width, H = cam.height;
  for (int64_t t : {int64_t{0}, int64_t{1'300'000}}) {
    absl::StatusOr<DecompositionRenders> r = (*d)->Render(cam, t);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(r->full.size(), size_t(W) * H * 3);
    // The full render is what the eval measures: the scene deformed at t (DeformedStore).
    ThreadPool pool(2);
    absl::StatusOr<GaussianStore> at_t = DeformedStore(*field, g, t, pool);
    ASSERT_TRUE(at_t.ok());
    absl::StatusOr<std::unique_ptr<DeviceScene>> dev = engine->Upload(*at_t);
    ASSERT_TRUE(dev.ok());
    RenderOptions ro;
    ro.background = background;
    RenderOutput ref;
    ASSERT_TRUE(engine->Render(**dev, cam, ro, &ref).ok());
    EXPECT_EQ(std::memcmp(ref.rgb.data(), r->full.data(), ref.rgb.size() * sizeof(float)), 0);

    // A conservative screen footprint of each dynamic Gaussian at t: 3 sigma of its largest axis
    // (+ 3DGS's 0.3 px^2 dilation and rounding: 3 px).
    const Eigen::Isometry3d T_cam_from_world = cam.T_world_from_cam.inverse();
    std::vector<Eigen::Vector3d> discs;  // u, v, radius
    for (uint32_t i : split.dynamic_rows) {
      const Eigen::Vector3d p = T_cam_from_world * Eigen::Vector3d(at_t->means[i * 3], at_t->means[i * 3 + 1],
                                                                   at_t->means[i * 3 + 2]);
      ASSERT_GT(p.z(), 1.0);
      const double s = std::exp(*std::max_element(&g.log_scales[i * 3], &g.log_scales[i * 3] + 3));
      discs.emplace_back(cam.fx * p.x() / p.z() + cam.cx, cam.fy * p.y() / p.z() + cam.cy, 3 * s * cam.fx / p.z() + 3);
    }
    int empty = 0, covered = 0;
    for (int y = 0; y < H; ++y) {
      for (int x = 0; x < W; ++x) {
        const size_t p = size_t(y) * W + x;
        const bool near = std::any_of(discs.begin(), discs.end(), [&](const Eigen::Vector3d& c) {
          return std::hypot(x - c.x(), y - c.y()) <= c.z();
        });
        if (near) {
          covered += r->dynamic_alpha[p] > 0.1f;
          continue;
        }
        ++empty;
        ASSERT_EQ(r->dynamic_alpha[p], 0.0f) << x << "," << y;
        for (int c = 0; c < 3; ++c) {
          ASSERT_EQ(r->dynamic_only[p * 3 + c], 0.0f) << x << "," << y;
          // Nothing dynamic in front or behind: static alone is the full render there.
          ASSERT_NEAR(r->static_only[p * 3 + c], r->full[p * 3 + c], 1e-6f) << x << "," << y;
        }
      }
    }
    EXPECT_GT(empty, W * H / 3);
    EXPECT_GT(covered, 20);  // the movers do show
  }
}

TEST(Decomposition, StaticSceneIsAllStaticAndItsStaticRenderIsTheFullOne) {
  const GaussianStore g = BandScene(30, 60);
  std::unique_ptr<Engine> engine = CpuEngine();
  absl::StatusOr<std::unique_ptr<Decomposer>> d = Decomposer::Create(*engine, g, nullptr, Eigen::Vector3f(0.1f, 0.2f, 0.3f));
  ASSERT_TRUE(d.ok()) << d.status();
  EXPECT_FALSE((*d)->split().has_field);
  EXPECT_EQ((*d)->split().static_rows.size(), g.size());
  for (int64_t t : {int64_t{0}, int64_t{900'000}}) {
    absl::StatusOr<DecompositionRenders> r = (*d)->Render(TopCamera(), t);
    ASSERT_TRUE(r.ok()) << r.status();
    ASSERT_EQ(r->static_only.size(), r->full.size());
    EXPECT_EQ(std::memcmp(r->static_only.data(), r->full.data(), r->full.size() * sizeof(float)), 0);
    EXPECT_TRUE(std::all_of(r->dynamic_only.begin(), r->dynamic_only.end(), [](float v) { return v == 0.0f; }));
    EXPECT_TRUE(std::all_of(r->dynamic_alpha.begin(), r->dynamic_alpha.end(), [](float v) { return v == 0.0f; }));
    EXPECT_GT(*std::max_element(r->full.begin(), r->full.end()), 0.35f);  // the scene is there
  }
  // A field needs SH degree 3.
  GaussianStore low = g;
  low.sh_degree = 0;
  low.sh.resize(g.size() * 3);
  EXPECT_FALSE(Decomposer::Create(*engine, low, std::make_shared<const field::DeformationField>(BandField()),
                                  Eigen::Vector3f::Zero()).ok());
}

TEST(Decomposition, WritesNamedPngsAndTheMaskOnlyWhenThereIsOne) {
  const std::string dir = TestDir("pngs");
  const GaussianStore g = BandScene(10, 10);
  std::unique_ptr<Engine> engine = CpuEngine();
  absl::StatusOr<std::unique_ptr<Decomposer>> d = Decomposer::Create(*engine, g, nullptr, Eigen::Vector3f::Zero());
  ASSERT_TRUE(d.ok());
  View v;
  v.name = "image_02/0000000011.png";
  v.frame = 11;
  v.camera = TopCamera();
  v.rgb8 = cv::Mat(v.camera.height, v.camera.width, CV_8UC3, cv::Scalar(10, 20, 30));
  EXPECT_EQ(DecompositionStem(v), "image_02_0000000011");
  absl::StatusOr<DecompositionRenders> r = (*d)->Render(v.camera, 0);
  ASSERT_TRUE(r.ok());
  ASSERT_TRUE(WriteDecompositionPngs(dir, v, *r).ok());
  for (const char* s : {"_full.png", "_static.png", "_dynamic.png"}) {
    const cv::Mat m = cv::imread(dir + "/image_02_0000000011" + s);
    EXPECT_EQ(m.cols, 96) << s;
    EXPECT_EQ(m.rows, 72) << s;
  }
  EXPECT_FALSE(fs::exists(dir + "/image_02_0000000011_mask.png"));
  v.dynamic_pixels.assign(96 * 72, 0);
  v.dynamic_pixels[5 * 96 + 7] = 1;
  ASSERT_TRUE(WriteDecompositionPngs(dir, v, *r).ok());
  const cv::Mat mask = cv::imread(dir + "/image_02_0000000011_mask.png");  // BGR
  ASSERT_FALSE(mask.empty());
  EXPECT_EQ(mask.at<cv::Vec3b>(5, 7)[2], (10 + 256) / 2);  // red channel, blended half-way to 255
  EXPECT_EQ(mask.at<cv::Vec3b>(6, 7)[2], 10);
  EXPECT_FALSE(WriteDecompositionPngs(dir + "/missing", v, *r).ok());
  fs::remove_all(dir);
}

TEST(EvalVideo, FpsFromTheFrameTimes) {
  EXPECT_DOUBLE_EQ(FpsFromTimes({0, 400'000, 800'000, 1'200'000}), 2.5);
  EXPECT_DOUBLE_EQ(FpsFromTimes({300'000, 0, 100'000, 200'000, 200'000}), 10.0);  // any order, repeats
  EXPECT_DOUBLE_EQ(FpsFromTimes({5}), 10.0);
  EXPECT_DOUBLE_EQ(FpsFromTimes({}), 10.0);
}

// Frames whose colour encodes their time; added out of order, they must come back sorted.
void WriteAndReadBack(const std::string& path) {
  EvalVideo video(path, 0);
  const int W = 61, H = 45;  // odd: padded to even
  const int64_t times[] = {300'000, 0, 200'000, 100'000, 400'000};
  for (int64_t t : times) {
    const int level = static_cast<int>(40 + t / 1000 * 0.4);  // 40 .. 200
    cv::Mat rendered(H, W, CV_8UC3, cv::Scalar(level, 0, 0)), gt(H, W, CV_8UC3, cv::Scalar(0, level, 0));
    ASSERT_TRUE(video.Add(t, "image_02", {rendered, gt}, {"rendered", "ground truth"}).ok());
  }
  // Another camera: skipped.
  ASSERT_TRUE(video.Add(50'000, "image_03", {cv::Mat(H, W, CV_8UC3), cv::Mat(H, W, CV_8UC3)}, {}).ok());
  EXPECT_EQ(video.size(), 5u);
  absl::StatusOr<VideoSummary> s = video.Write();
  ASSERT_TRUE(s.ok()) << s.status();
  EXPECT_EQ(s->frames, 5);
  EXPECT_EQ(s->width, 122);
  EXPECT_EQ(s->height, 46);
  EXPECT_NEAR(s->fps, 10.0, 1e-9);
  cv::VideoCapture cap(path);
  ASSERT_TRUE(cap.isOpened()) << path;
  std::vector<cv::Mat> frames;
  cv::Mat f;
  while (cap.read(f)) frames.push_back(f.clone());
  ASSERT_EQ(frames.size(), 5u) << path;
  for (size_t i = 0; i < frames.size(); ++i) {
    EXPECT_EQ(frames[i].cols, 122);
    EXPECT_EQ(frames[i].rows, 46);
    const cv::Vec3b left = frames[i].at<cv::Vec3b>(20, 30), right = frames[i].at<cv::Vec3b>(20, 91);  // BGR
    const int level = static_cast<int>(40 + i * 40);
    EXPECT_NEAR(left[2], level, 12) << path << " frame " << i;  // rendered: red
    EXPECT_NEAR(right[1], level, 12) << path << " frame " << i;  // ground truth: green
  }
}

TEST(EvalVideo, AviWrittenInTimeOrderAndReadBack) {
  const std::string dir = TestDir("avi");
  WriteAndReadBack(dir + "/eval.avi");
  fs::remove_all(dir);
}

TEST(EvalVideo, Mp4WrittenInTimeOrderAndReadBack) {
  const std::string dir = TestDir("mp4");
  WriteAndReadBack(dir + "/eval.MP4");
  fs::remove_all(dir);
}

TEST(EvalVideo, BadPathsAreClearErrors) {
  const std::string dir = TestDir("bad");
  EXPECT_TRUE(absl::IsNotFound(CheckVideoPath(dir + "/no/such/dir/v.avi")));
  EXPECT_TRUE(absl::IsInvalidArgument(CheckVideoPath(dir + "/v.mkv")));
  EXPECT_TRUE(absl::IsInvalidArgument(CheckVideoPath(dir + "/v")));
  fs::create_directories(dir + "/d.avi");
  EXPECT_TRUE(absl::IsInvalidArgument(CheckVideoPath(dir + "/d.avi")));
  EXPECT_TRUE(CheckVideoPath(dir + "/v.avi").ok());
  EXPECT_TRUE(absl::IsInvalidArgument(WriteVideo(dir + "/v.avi", {}, 10).status()));
  EXPECT_FALSE(WriteVideo(dir + "/no/v.avi", {cv::Mat(4, 4, CV_8UC3)}, 10).ok());
  EXPECT_FALSE(fs::exists(dir + "/v.avi"));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace streetsim::train
