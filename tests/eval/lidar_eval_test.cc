// LiDAR evaluation (scene/eval/lidar_eval.h) and `streetsim eval`'s LiDAR keys, on the shared
// KITTI clip with an initial scene from LiDAR.
#include "scene/eval/lidar_eval.h"

#include <unistd.h>

#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>

#include "gtest/gtest.h"
#include "tests/common/cli_runner.h"
#include "render/common/thread_pool.h"
#include "scene/gaussians/ply_io.h"
#include "scene/init/initial_scene.h"
#include "scene/log/open_log.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;
const std::string kKitti = std::string(STREETSIM_DATA_DIR) + "/kitti_raw/2011_09_26/2011_09_26_drive_sfnd_sync";

TEST(LidarEval, ChamferOfKnownClouds) {
  std::vector<Eigen::Vector3f> a;
  for (int i = 0; i < 10; ++i) {
    for (int j = 0; j < 10; ++j) a.emplace_back(i, j, 0);
  }
  EXPECT_DOUBLE_EQ(ChamferDistanceM(a, a, 1000), 0.0);
  std::vector<Eigen::Vector3f> b = a;
  for (auto& p : b) p.z() += 0.25f;
  EXPECT_NEAR(ChamferDistanceM(a, b, 1000), 0.25, 1e-6);
  // Thinned queries (every 4th) on a uniform offset give the same answer.
  EXPECT_NEAR(ChamferDistanceM(a, b, 25), 0.25, 1e-6);
  // One extra far point in b: only the b->a direction sees it.
  b.emplace_back(0, 0, 100.25f);
  EXPECT_NEAR(ChamferDistanceM(a, b, 1000), 0.5 * (0.25 + (100 * 0.25 + 100.25) / 101), 1e-4);
  EXPECT_EQ(ChamferDistanceM(a, {}, 1000), -1);
  // Spread over threads: the same bits.
  std::vector<Eigen::Vector3f> c, d;
  for (int i = 0; i < 5000; ++i) {
    c.emplace_back(std::sin(i * 0.37f) * 20, std::cos(i * 0.11f) * 20, i % 7);
    d.emplace_back(std::sin(i * 0.53f) * 20, std::cos(i * 0.29f) * 20, i % 5);
  }
  ThreadPool pool(3);
  EXPECT_EQ(ChamferDistanceM(c, d, 3000, &pool), ChamferDistanceM(c, d, 3000));
}

TEST(LidarEval, CompareRangeImagesCountsRays) {
  LidarModel model = KittiHdl64e(16);
  const size_t P = static_cast<size_t>(model.beams()) * model.columns;
  std::vector<float> rr(P, 0), ri(P, 0), tr(P, 0), ti(P, 0);
  // 4 rays return in both (range errors 0.1, 0.2, 0.3, 0.4; intensity errors 0.1 each), one only
  // rendered, one only real.
  for (int k = 0; k < 4; ++k) {
    rr[k] = 10;
    tr[k] = 10 + 0.1f * (k + 1);
    ri[k] = 0.5f;
    ti[k] = 0.6f;
  }
  rr[10] = 5;
  tr[11] = 5;
  const LidarFrameMetrics m = CompareRangeImages(model, rr, ri, tr, ti, 1000);
  EXPECT_EQ(m.rays, 4u);
  EXPECT_NEAR(m.range_median_abs_m, 0.3, 1e-5);  // upper median of 4
  EXPECT_NEAR(m.intensity_rmse, 0.1, 1e-6);
  EXPECT_NEAR(m.drop_accuracy, double(P - 2) / P, 1e-12);
  EXPECT_GT(m.chamfer_m, 0);
}

TEST(LidarEval, ReflectancePropertyIsReadWhenPresent) {
  const std::string dir = fs::temp_directory_path() / "streetsim_lidar_eval_ply";
  fs::create_directories(dir);
  GaussianStore store;
  store.Resize(3);
  for (int i = 0; i < 3; ++i) store.rotations[4 * i] = 1;
  const absl::Status written = WriteGaussianPly(store, dir + "/plain.ply");
  ASSERT_TRUE(written.ok()) << written;
  absl::StatusOr<std::optional<std::vector<float>>> r = ReadPlyReflectance(dir + "/plain.ply", 3);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->has_value());
  {
    std::ofstream f(dir + "/refl.ply", std::ios::binary);
    f << "ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty uchar tag\n"
         "property float reflectance\nend_header\n";
    const float x0 = 1, r0 = 0.25f, x1 = 2, r1 = 0.75f;
    const char tag = 7;
    f.write(reinterpret_cast<const char*>(&x0), 4).write(&tag, 1).write(reinterpret_cast<const char*>(&r0), 4);
    f.write(reinterpret_cast<const char*>(&x1), 4).write(&tag, 1).write(reinterpret_cast<const char*>(&r1), 4);
  }
  r = ReadPlyReflectance(dir + "/refl.ply", 2);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_TRUE(r->has_value());
  EXPECT_EQ((**r)[0], 0.25f);
  EXPECT_EQ((**r)[1], 0.75f);
  EXPECT_FALSE(ReadPlyReflectance(dir + "/refl.ply", 3).ok());  // count mismatch
  EXPECT_FALSE(ReadPlyReflectance(dir + "/missing.ply", 3).ok());
  fs::remove_all(dir);
}

const DriveLog& Kitti() {
  static const DriveLog log = *OpenLog(kKitti);
  return log;
}

GaussianStore InitScene() {
  InitOptions options;
  options.frames = {0, 78, 4};
  absl::StatusOr<GaussianStore> store = BuildInitialScene(Kitti(), options);
  EXPECT_TRUE(store.ok()) << store.status();
  return *store;
}

TEST(LidarEval, KittiInitSceneIsSensibleAndAShiftedSceneIsWorse) {
  const GaussianStore scene = InitScene();
  LidarEvalOptions opt;
  opt.columns = 1024;
  const std::vector<int> frames = {21, 41};
  absl::StatusOr<LidarEvalResult> good = EvaluateLidar(Kitti(), frames, scene, nullptr, opt);
  ASSERT_TRUE(good.ok()) << good.status();
  ASSERT_EQ(good->frames.size(), 2u);
  for (const LidarFrameMetrics& m : good->frames) {
    EXPECT_GT(m.rays, 5000u) << m.frame;
    EXPECT_TRUE(std::isfinite(m.range_median_abs_m) && m.range_median_abs_m >= 0) << m.frame;
    EXPECT_LT(m.range_median_abs_m, 3.0) << m.frame;
    EXPECT_GT(m.chamfer_m, 0) << m.frame;
    EXPECT_LT(m.chamfer_m, 6.0) << m.frame;
    EXPECT_GT(m.drop_accuracy, 0.3) << m.frame;
    EXPECT_LE(m.drop_accuracy, 1.0) << m.frame;
    // Constant 0.5 against KITTI reflectance (mostly 0..0.6): an RMSE well inside (0, 0.6).
    EXPECT_GT(m.intensity_rmse, 0.05) << m.frame;
    EXPECT_LT(m.intensity_rmse, 0.6) << m.frame;
  }
  EXPECT_EQ(good->mean.rays, good->frames[0].rays + good->frames[1].rays);

  GaussianStore shifted = scene;
  for (size_t i = 0; i < shifted.size(); ++i) shifted.means[3 * i + 1] += 2.0f;  // 2 m to the side
  absl::StatusOr<LidarEvalResult> bad = EvaluateLidar(Kitti(), frames, shifted, nullptr, opt);
  ASSERT_TRUE(bad.ok()) << bad.status();
  EXPECT_GT(bad->mean.chamfer_m, good->mean.chamfer_m + 0.3)
      << "shifted " << bad->mean.chamfer_m << " vs " << good->mean.chamfer_m;
  EXPECT_GT(bad->mean.range_median_abs_m, good->mean.range_median_abs_m);

  std::printf("init scene: median %.3f m, chamfer %.3f m, drop acc %.4f, intensity rmse %.4f, %zu rays\n"
              "shifted 2 m: median %.3f m, chamfer %.3f m, drop acc %.4f, intensity rmse %.4f, %zu rays\n",
              good->mean.range_median_abs_m, good->mean.chamfer_m, good->mean.drop_accuracy,
              good->mean.intensity_rmse, good->mean.rays, bad->mean.range_median_abs_m, bad->mean.chamfer_m,
              bad->mean.drop_accuracy, bad->mean.intensity_rmse, bad->mean.rays);

  // A frame index outside the log is an error, not a crash.
  EXPECT_FALSE(EvaluateLidar(Kitti(), {1000}, scene, nullptr, opt).ok());
}

TEST(LidarEval, LogEgoPoseInterpolatesBetweenFrames) {
  const DriveLog& log = Kitti();
  const Frame& a = log.frames[10];
  const Frame& b = log.frames[11];
  const Eigen::Isometry3d mid = LogEgoPoseAt(log, (a.time_us + b.time_us) / 2);
  EXPECT_LT((mid.translation() - 0.5 * (a.T_world_from_ego.translation() + b.T_world_from_ego.translation())).norm(),
            1e-9);
  EXPECT_TRUE(LogEgoPoseAt(log, a.time_us).isApprox(a.T_world_from_ego, 1e-12));
  EXPECT_TRUE(LogEgoPoseAt(log, -1'000'000'000).isApprox(log.frames.front().T_world_from_ego, 1e-12));
  EXPECT_TRUE(LogEgoPoseAt(log, log.frames.back().time_us + 1).isApprox(log.frames.back().T_world_from_ego, 1e-12));
}

struct Cli {
  int code;
  std::string out, err;
};
Cli RunCli(const std::string& args) {
  const auto dir = fs::temp_directory_path();
  const std::string out = (dir / ("streetsim_lidar_eval_out." + std::to_string(getpid()) + ".txt")).string();
  const std::string err = (dir / ("streetsim_lidar_eval_err." + std::to_string(getpid()) + ".txt")).string();
  const int status =
      std::system((std::string(STREETSIM_BINARY_DIR) + "/bin/streetsim " + cli_test::WithoutActorsUnlessNamed(args) + " >" + out + " 2>" + err).c_str());
  auto slurp = [](const std::string& p) {
    std::ifstream f(p);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
  };
  Cli r{WEXITSTATUS(status), slurp(out), slurp(err)};
  fs::remove(out);
  fs::remove(err);
  return r;
}

TEST(LidarEval, EvalCommandReportsLidarKeys) {
  const std::string dir = fs::temp_directory_path() / "streetsim_lidar_eval_scene";
  fs::remove_all(dir);
  fs::create_directories(dir);
  ASSERT_TRUE(WriteGaussianPly(InitScene(), dir + "/scene.ply").ok());
  const std::string base = "eval --scene " + dir + " --log " + kKitti + " --holdout-every 20 --resolution-scale 0.2";
  Cli r = RunCli(base + " --lidar-columns 1024");
  ASSERT_EQ(r.code, 0) << r.err;
  nlohmann::json j = nlohmann::json::parse(r.out);
  ASSERT_EQ(j["frames"].size(), 3u);  // frames 19, 39, 59
  for (const char* key : {"lidar_range_median_abs_m", "lidar_chamfer_m", "lidar_drop_accuracy", "lidar_intensity_rmse"}) {
    ASSERT_TRUE(j["mean"][key].is_number()) << key;
    EXPECT_TRUE(std::isfinite(j["mean"][key].get<double>())) << key;
    for (const auto& f : j["frames"]) EXPECT_TRUE(f[key].is_number()) << key;
  }
  EXPECT_GT(j["mean"]["lidar_rays"].get<int>(), 10000);
  EXPECT_NE(r.err.find("chamfer"), std::string::npos);
  EXPECT_NE(r.err.find("constant 0.5"), std::string::npos);

  r = RunCli(base + " --no-lidar");
  ASSERT_EQ(r.code, 0) << r.err;
  j = nlohmann::json::parse(r.out);
  EXPECT_FALSE(j["mean"].contains("lidar_chamfer_m"));
  EXPECT_TRUE(j["mean"]["psnr"].is_number());

  r = RunCli(base + " --lidar-columns 0");
  EXPECT_EQ(r.code, 2) << r.err;
  fs::remove_all(dir);
}

}  // namespace
}  // namespace streetsim::train
