// A clip set (DIR/clips.json, docs/training.md "Clips") under the data root is listed as one
// scene (docs/server.md "Clip sets") with the merged manifest of its clips, while each clip
// directory stays a scene of its own; a set whose clips disagree (rig, overlapping trajectories)
// or whose clips.json points out of the set is listed with an error naming the clip or file.
// Rendering a set: clip_set_serve_test.cc.
#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "gtest/gtest.h"
#include "scene/gaussians/ply_io.h"
#include "scene/gaussians/synthetic_street.h"
#include "scene/train/clips.h"
#include "server/scene_registry.h"

namespace streetsim::server {
namespace {

namespace fs = std::filesystem;

// scene.json of clip k: one camera (wider in clip `wide_clip`), time range [400 ms k, 400 ms k +
// 300 ms], an ego trajectory over it (starting at `traj_start_us` + 400 ms k).
std::string ClipSceneJson(int k, int wide_clip, int64_t traj_start_us) {
  const int64_t t0 = 400'000 * k, t1 = t0 + 300'000;
  const int width = k == wide_clip ? 256 : 128;
  return "{\"time_range_us\": [" + std::to_string(t0) + ", " + std::to_string(t1) +
         "], \"cameras\": [{\"sensor_id\": \"cam_front\", \"width\": " + std::to_string(width) +
         ", \"height\": 64, \"fx\": 80, \"fy\": 80, \"cx\": 63.5, \"cy\": 31.5,"
         " \"T_ego_from_cam\": [0,0,1,1.5, -1,0,0,0, 0,-1,0,1.65, 0,0,0,1]}],"
         " \"ego_trajectory\": [{\"time_us\": " + std::to_string(traj_start_us + t0) +
         ", \"T_world_from_ego\": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}, {\"time_us\": " + std::to_string(t1) +
         ", \"T_world_from_ego\": [1,0,0,3, 0,1,0,0, 0,0,1,0, 0,0,0,1]}]}";
}

// ROOT/NAME: two clips (frames [0, 4), [4, 8)) with a scene.ply and scene.json each, clips.json.
void WriteSet(const fs::path& root, const std::string& name, int wide_clip = -1, int64_t traj_start_us = 0,
              const std::string& clip1_dir = "") {
  SyntheticStreetOptions o;
  o.num_gaussians = 200;
  train::ClipSet set;
  set.clip_frames = 4;
  set.num_frames = 8;
  for (int k = 0; k < 2; ++k) {
    const fs::path dir = root / name / train::ClipDirName(k);
    fs::create_directories(dir);
    o.seed = 1 + k;
    ASSERT_TRUE(WriteGaussianPly(MakeSyntheticStreet(o), (dir / "scene.ply").string()).ok());
    std::ofstream((dir / "scene.json").string()) << ClipSceneJson(k, wide_clip, k == 1 ? traj_start_us : 0);
    train::ClipEntry e;
    e.frames = {4 * k, 4 * k + 4};
    e.start_us = 400'000 * k;
    e.end_us = 400'000 * k + 300'000;
    e.dir = k == 1 && !clip1_dir.empty() ? clip1_dir : train::ClipDirName(k);
    e.done = true;
    set.clips.push_back(e);
  }
  ASSERT_TRUE(train::WriteClipSet(set, (root / name).string()).ok());
}

fs::path TempRoot(const std::string& tag) {
  const fs::path root = fs::path(::testing::TempDir()) /
                        ("streetsim_clip_set_registry_" + tag + "_" + std::to_string(getpid()));
  fs::remove_all(root);
  fs::create_directories(root);
  return root;
}

TEST(ClipSetRegistry, ListedAsOneSceneWithTheMergedManifestClipsServedAlone) {
  const fs::path root = TempRoot("merged");
  WriteSet(root, "set");
  SyntheticStreetOptions o;
  o.num_gaussians = 200;
  for (const char* p : {"set/scene.ply", "plain/scene.ply"}) {
    fs::create_directories((root / p).parent_path());
    ASSERT_TRUE(WriteGaussianPly(MakeSyntheticStreet(o), (root / p).string()).ok());
  }

  SceneRegistry registry(root.string(), "", nullptr);
  std::map<std::string, v1::Scene> by_name;
  for (const v1::Scene& s : registry.List()) by_name[s.name()] = s;
  for (const char* name : {"set", "set/clip_000", "set/clip_001", "plain"}) {
    ASSERT_TRUE(by_name.count(name)) << name;
    EXPECT_TRUE(by_name[name].error().empty()) << name << ": " << by_name[name].error();
  }
  // The clip set wins over a stale scene.ply beside clips.json: its range is the clips' union.
  absl::StatusOr<std::shared_ptr<const SceneManifest>> m = registry.Manifest("set");
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_TRUE((*m)->has_time_range);
  EXPECT_EQ((*m)->start_us, 0);
  EXPECT_EQ((*m)->end_us, 700'000);
  ASSERT_EQ((*m)->cameras.size(), 1u);
  EXPECT_EQ((*m)->cameras[0].intrinsics.width, 128);
  ASSERT_EQ((*m)->ego_trajectory.size(), 4u);
  EXPECT_EQ((*m)->ego_trajectory[1].time_us, 300'000);
  EXPECT_EQ((*m)->ego_trajectory[2].time_us, 400'000);
  EXPECT_FALSE((*m)->background.has_value());  // per clip: ClipSetSceneField::BackgroundAt
  // Between the clips the ego pose interpolates from clip 0's last pose to clip 1's first.
  EXPECT_NEAR((*m)->EgoPoseAt(350'000)->translation().x(), 1.5, 1e-9);
  fs::remove_all(root);
}

TEST(ClipSetRegistry, ClipsThatDisagreeOrLeaveTheSetAreListedWithTheClipNamed) {
  const fs::path root = TempRoot("bad");
  WriteSet(root, "rig", /*wide_clip=*/1);
  WriteSet(root, "overlap", -1, /*traj_start_us=*/-200'000);  // clip 1's trajectory starts at 200 ms
  WriteSet(root, "hostile", -1, 0, "../rig/clip_000");
  WriteSet(root, "missing");
  fs::remove_all(root / "missing/clip_001");
  fs::create_directories(root / "damaged");
  std::ofstream((root / "damaged/clips.json").string()) << "{\"clips\": [";

  SceneRegistry registry(root.string(), "", nullptr);
  std::map<std::string, v1::Scene> by_name;
  for (const v1::Scene& s : registry.List()) by_name[s.name()] = s;
  auto expect_error = [&](const std::string& name, const std::vector<std::string>& parts) {
    ASSERT_TRUE(by_name.count(name)) << name;
    for (const std::string& part : parts) {
      EXPECT_NE(by_name[name].error().find(part), std::string::npos) << name << ": " << by_name[name].error();
    }
    absl::StatusOr<v1::Scene> load = registry.Load(name, false, nullptr);
    ASSERT_FALSE(load.ok()) << name;
    EXPECT_EQ(load.status().code(), absl::StatusCode::kFailedPrecondition) << load.status();
    EXPECT_EQ(registry.Acquire(name, nullptr).status().code(), absl::StatusCode::kFailedPrecondition);
  };
  expect_error("rig", {"clip_001", "rig"});
  expect_error("overlap", {"clip_001", "trajectory"});
  expect_error("hostile", {"clips.json"});
  expect_error("missing", {"clip_001"});
  expect_error("damaged", {"clips.json"});
  EXPECT_TRUE(by_name["rig/clip_001"].error().empty());  // each clip is still a scene of its own
  fs::remove_all(root);
}

// Scenes trained with --field extended are served since (tests/server/ext_field_scene_test.cc,
// which also covers a damaged or foreign field_ext.bin being refused with the file named).

}  // namespace
}  // namespace streetsim::server
