// A clip set (DIR/clips.json, docs/training.md "Clips") under the data root: the server lists it
// with an error that names its clips and refuses to load it (no half-served log), while each clip
// directory is a scene of its own.
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

TEST(ClipSetRegistry, ListedWithAnErrorAndRefusedClipsServedAlone) {
  const fs::path root = fs::path(::testing::TempDir()) / ("streetsim_clip_set_registry_" + std::to_string(getpid()));
  fs::remove_all(root);
  fs::create_directories(root / "set/clip_000");
  fs::create_directories(root / "set/clip_001");
  SyntheticStreetOptions o;
  o.num_gaussians = 200;
  const GaussianStore g = MakeSyntheticStreet(o);
  for (const char* p : {"set/clip_000/scene.ply", "set/clip_001/scene.ply", "set/scene.ply", "plain/scene.ply"}) {
    fs::create_directories((root / p).parent_path());
    ASSERT_TRUE(WriteGaussianPly(g, (root / p).string()).ok());
  }
  train::ClipSet set;
  set.clip_frames = 4;
  set.num_frames = 8;
  for (int k = 0; k < 2; ++k) {
    train::ClipEntry e;
    e.frames = {4 * k, 4 * k + 4};
    e.start_us = 400'000 * k;
    e.end_us = 400'000 * k + 300'000;
    e.dir = train::ClipDirName(k);
    e.done = true;
    set.clips.push_back(e);
  }
  ASSERT_TRUE(train::WriteClipSet(set, (root / "set").string()).ok());

  SceneRegistry registry(root.string(), "", nullptr);
  std::map<std::string, v1::Scene> by_name;
  for (const v1::Scene& s : registry.List()) by_name[s.name()] = s;
  ASSERT_TRUE(by_name.count("set"));  // the clip set wins over a stale scene.ply beside clips.json
  EXPECT_NE(by_name["set"].error().find("clip set"), std::string::npos) << by_name["set"].error();
  EXPECT_NE(by_name["set"].error().find("set/clip_000"), std::string::npos) << by_name["set"].error();
  for (const char* clip : {"set/clip_000", "set/clip_001", "plain"}) {
    ASSERT_TRUE(by_name.count(clip)) << clip;
    EXPECT_TRUE(by_name[clip].error().empty()) << clip << ": " << by_name[clip].error();
  }
  absl::StatusOr<v1::Scene> load = registry.Load("set", false, nullptr);
  ASSERT_FALSE(load.ok());
  EXPECT_EQ(load.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(load.status().message().find("clip set"), std::string::npos) << load.status();
  EXPECT_EQ(registry.Acquire("set", nullptr).status().code(), absl::StatusCode::kFailedPrecondition);
  fs::remove_all(root);
}

// A scene trained with --field extended (field_ext.bin beside field.bin) is refused with the file
// named rather than served with the base field alone.
TEST(ExtendedSceneRegistry, RefusedWithTheFileNamed) {
  const fs::path root = fs::path(::testing::TempDir()) / ("streetsim_ext_registry_" + std::to_string(getpid()));
  fs::remove_all(root);
  fs::create_directories(root / "ext");
  SyntheticStreetOptions o;
  o.num_gaussians = 200;
  ASSERT_TRUE(WriteGaussianPly(MakeSyntheticStreet(o), (root / "ext/scene.ply").string()).ok());
  for (const char* f : {"field.bin", "field_ext.bin"}) {
    std::ofstream((root / "ext" / f).string()) << "not read: refused before";
  }
  SceneRegistry registry(root.string(), "", nullptr);
  absl::StatusOr<v1::Scene> load = registry.Load("ext", true, nullptr);
  absl::Status status = load.ok() ? absl::OkStatus() : load.status();
  if (load.ok()) {  // a finished load reports its error in the scene
    EXPECT_NE(load->error().find("field_ext.bin"), std::string::npos) << load->error();
    EXPECT_NE(load->error().find("--field extended"), std::string::npos) << load->error();
  } else {
    EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
    EXPECT_NE(status.message().find("field_ext.bin"), std::string::npos) << status;
  }
  EXPECT_FALSE(registry.Acquire("ext", nullptr).ok());
  fs::remove_all(root);
}

}  // namespace
}  // namespace streetsim::server
