// The served scene (scene/eval/served_scene.h, what `streetsim eval --served` renders): on a field
// that moves a band of Gaussians, the served renders equal the full field's when nothing is baked,
// stay within the skip's bound at the server's thresholds, and lose the band's motion when every
// Gaussian is baked; the LiDAR path's stores are the served ones.
#include <algorithm>
#include <cmath>
#include <memory>

#include "gtest/gtest.h"
#include "render/engine.h"
#include "scene/field/static_skip.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/served_scene.h"
#include "tests/train/band_scene.h"

namespace streetsim::train {
namespace {

using testing::BandField;
using testing::BandScene;
using testing::CpuEngine;
using testing::TopCamera;

// Max abs difference of two renders' RGB.
float MaxDiff(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  float m = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) m = std::max(m, std::abs(a[i] - b[i]));
  return m;
}

class ServedSceneTest : public ::testing::Test {
 protected:
  std::vector<float> Render(const SceneForView& sv, int64_t time_us) {
    View v;
    v.camera = TopCamera();
    v.time_us = time_us;
    absl::StatusOr<const DeviceScene*> s = sv(v);
    EXPECT_TRUE(s.ok()) << s.status();
    RenderOutput out;
    EXPECT_TRUE(engine_->Render(**s, v.camera, RenderOptions{}, &out).ok());
    return out.rgb;
  }
  std::shared_ptr<field::ServedScene> Served(double motion_m, double sh) {
    field::StaticSkipOptions o;
    o.motion_threshold_m = motion_m;
    o.sh_threshold = sh;
    absl::StatusOr<std::shared_ptr<field::ServedScene>> s = MakeServedScene(field_, scene_, o);
    EXPECT_TRUE(s.ok()) << s.status();
    return *s;
  }

  std::shared_ptr<const field::DeformationField> field_ = std::make_shared<const field::DeformationField>(BandField());
  GaussianStore scene_ = BandScene(30, 60);
  std::unique_ptr<Engine> engine_ = CpuEngine();
};

TEST_F(ServedSceneTest, RendersAsTheFullFieldUnlessBaked) {
  absl::StatusOr<SceneForView> full = MakeSceneForView(*engine_, scene_, field_);
  ASSERT_TRUE(full.ok());
  const std::shared_ptr<field::ServedScene> none = Served(0, 0), by_default = Served(0.01, 0.01),
                                            all = Served(1e9, 1e9);
  EXPECT_EQ(none->num_dynamic(), scene_.size());
  EXPECT_GT(by_default->num_dynamic(), 20u);              // the band
  EXPECT_LT(by_default->num_dynamic(), scene_.size());    // not the far Gaussians
  EXPECT_EQ(all->num_dynamic(), 0u);
  absl::StatusOr<SceneForView> sv_none = MakeServedSceneForView(*engine_, none);
  absl::StatusOr<SceneForView> sv_default = MakeServedSceneForView(*engine_, by_default);
  absl::StatusOr<SceneForView> sv_all = MakeServedSceneForView(*engine_, all);
  ASSERT_TRUE(sv_none.ok() && sv_default.ok() && sv_all.ok());
  float baked_diff = 0;
  for (int64_t t : {0, 350'000, 1'000'000, 2'000'000}) {
    const std::vector<float> ref = Render(*full, t);
    EXPECT_LT(MaxDiff(Render(*sv_none, t), ref), 1e-4f) << t;
    EXPECT_LT(MaxDiff(Render(*sv_default, t), ref), 1e-4f) << t;  // the far Gaussians do not move
    baked_diff = std::max(baked_diff, MaxDiff(Render(*sv_all, t), ref));
  }
  // Everything baked: the band sits at its time-mean and the images differ where it moves.
  EXPECT_GT(baked_diff, 0.02f);
}

TEST_F(ServedSceneTest, LidarStoresAreTheServedOnes) {
  const std::shared_ptr<field::ServedScene> s = Served(0.01, 0.01);
  const StoreAtTime at = MakeServedStoreAtTime(s);
  ThreadPool pool(1);
  for (int64_t t : {0, 700'000, 2'000'000}) {
    absl::StatusOr<GaussianStore> g = at(t);
    ASSERT_TRUE(g.ok());
    absl::StatusOr<GaussianStore> ref = DeformedStore(*field_, scene_, t, pool);
    ASSERT_TRUE(ref.ok());
    ASSERT_EQ(g->means.size(), ref->means.size());
    float m = 0;
    for (size_t i = 0; i < g->means.size(); ++i) m = std::max(m, std::abs(g->means[i] - ref->means[i]));
    EXPECT_LT(m, 0.01f) << t;  // within the motion threshold
  }
}

TEST_F(ServedSceneTest, RefusesNoFieldAndLowDegree) {
  EXPECT_EQ(MakeServedScene(nullptr, scene_, {}).status().code(), absl::StatusCode::kInvalidArgument);
  GaussianStore low = BandScene(3, 3);
  low.sh_degree = 0;
  low.sh.resize(low.size() * 3);
  EXPECT_EQ(MakeServedScene(field_, low, {}).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(MakeServedSceneForView(*engine_, nullptr).ok());
}

}  // namespace
}  // namespace streetsim::train
