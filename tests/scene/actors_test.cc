// Actors (scene/actors/, docs/actors.md) on a synthetic street with known objects: extraction
// finds each moving object and its Gaussians (precision / recall), a removal changes only the
// actor's own pixels, a moved actor renders as its Gaussians transformed, SH turns with the body,
// bad edits are refused, and the set's files round-trip and refuse another scene.
#include <cstdio>
#include <fstream>
#include <random>

#include "gtest/gtest.h"
#include "render/common/projection_math.h"
#include "render/engine.h"
#include "scene/actors/actor_edits.h"
#include "scene/actors/actor_extraction.h"
#include "scene/actors/actor_set.h"
#include "scene/actors/rigid_gaussians.h"
#include "scene/gaussians/ply_io.h"
#include "tests/common/box_scans.h"
#include "tests/common/scratch_dir.h"

namespace streetsim::actors {
namespace {

// The tracker tests' street (tests/common/box_scans.h): a truck that stops after scan 12, an
// oncoming car, a parked car and a wall.
constexpr int kScans = 20;
int64_t ScanTimeUs(int k) { return testing::StreetScanTimeUs(k); }
double TruckX(int k) { return testing::StreetTruckX(k); }
double CarX(int k) { return testing::StreetCarX(k); }
const Eigen::Vector3d kTruckSize(12, 2.5, 3.0), kCarSize(4.5, 1.8, 1.5);

// What each row of the synthetic scene is.
enum class Part : uint8_t { kTruck, kCar, kTruckSmear, kParked, kWall, kGround };

// A dynamic scene as a trained one would be: Gaussians on the truck and the car that follow them,
// a smear of the truck where it stood in scans 0 and 6 (what a static stage leaves), and still
// Gaussians on the parked car, the wall and the road (under both paths). Isotropic, SH degree 0.
struct Street {
  GaussianStore canonical;
  std::vector<Part> part;
  std::vector<Eigen::Vector3f> local;  // truck / car rows: offset from the box's low corner

  void Add(const Eigen::Vector3f& p, Part what, const Eigen::Vector3f& colour, float opacity_logit = 2) {
    const size_t i = canonical.size();
    canonical.Resize(i + 1);
    for (int a = 0; a < 3; ++a) {
      canonical.means[i * 3 + a] = p[a];
      canonical.log_scales[i * 3 + a] = std::log(0.12f);
      canonical.sh[i * 3 + a] = (colour[a] - 0.5f) / static_cast<float>(projection::kShC0);
    }
    canonical.rotations[i * 4] = 1;
    canonical.opacity_logits[i] = opacity_logit;
    part.push_back(what);
    local.push_back(p);
  }
  void AddBoxSurface(const Eigen::Vector3d& lo, const Eigen::Vector3d& size, Part what, const Eigen::Vector3f& colour,
                     float opacity_logit = 2) {
    for (double x = 0.1; x < size.x(); x += 0.4) {
      for (double z = 0.1; z < size.z(); z += 0.4) {
        for (double y : {0.1, size.y() - 0.1}) {
          Add((lo + Eigen::Vector3d(x, y, z)).cast<float>(), what, colour, opacity_logit);
        }
      }
    }
    if (what == Part::kTruck || what == Part::kCar) {
      for (size_t i = part.size(); i-- > 0 && part[i] == what;) local[i] -= lo.cast<float>();
    }
  }

  Street() {
    AddBoxSurface({TruckX(0), -4.25, 0.3}, kTruckSize, Part::kTruck, {0.9f, 0.2f, 0.1f});
    AddBoxSurface({CarX(0), 4.1, 0.3}, kCarSize, Part::kCar, {0.1f, 0.3f, 0.9f});
    for (int k : {0, 6}) AddBoxSurface({TruckX(k), -4.25, 0.3}, kTruckSize, Part::kTruckSmear, {0.6f, 0.3f, 0.2f}, -1);
    AddBoxSurface({5, 9, 0.3}, {4.5, 1.8, 1.5}, Part::kParked, {0.2f, 0.8f, 0.2f});
    for (double x = -30; x <= 30; x += 0.5) {
      for (double z = 0.3; z <= 3; z += 0.5) Add(Eigen::Vector3f(x, 14, z), Part::kWall, {0.7f, 0.7f, 0.7f});
      for (double y = -6; y <= 8; y += 0.5) Add(Eigen::Vector3f(x, y, 0.02f), Part::kGround, {0.3f, 0.3f, 0.3f});
    }
  }

  // The scene at a time: the truck and the car where the scans see them.
  GaussianStore At(int64_t time_us) const {
    const int k = std::clamp(static_cast<int>((time_us - ScanTimeUs(0) + 50'000) / 100'000), 0, kScans - 1);
    GaussianStore g = canonical;
    for (size_t i = 0; i < part.size(); ++i) {
      Eigen::Vector3f p;
      if (part[i] == Part::kTruck) {
        p = local[i] + Eigen::Vector3f(TruckX(k), -4.25f, 0.3f);
      } else if (part[i] == Part::kCar) {
        p = local[i] + Eigen::Vector3f(CarX(k), 4.1f, 0.3f);
      } else {
        continue;
      }
      for (int a = 0; a < 3; ++a) g.means[i * 3 + a] = p[a];
    }
    return g;
  }
};

struct Extracted {
  Street street;
  ActorSet set;
};

Extracted Extract(bool static_scene = false) {
  Extracted e;
  MovingObjectOptions tracking;
  tracking.keep_points = true;
  const std::vector<MovingObjectTrack> tracks = TrackObjectsInLevelScans(testing::Street(), tracking);
  GaussianStore current;
  const GaussiansAt at = [&](int64_t t) -> absl::StatusOr<const GaussianStore*> {
    if (static_scene) return &e.street.canonical;
    current = e.street.At(t);
    return &current;
  };
  absl::StatusOr<ActorSet> set = ExtractActors(tracks, at, {});
  EXPECT_TRUE(set.ok()) << set.status();
  if (set.ok()) e.set = std::move(*set);
  e.set.scene_gaussians = e.street.canonical.size();
  return e;
}

// Precision and recall of `rows` against the rows of `part`.
std::pair<double, double> PrecisionRecall(const std::vector<uint32_t>& rows, const std::vector<Part>& parts, Part part) {
  size_t hit = 0, truth = 0;
  for (uint32_t r : rows) hit += parts[r] == part;
  for (Part p : parts) truth += p == part;
  return {rows.empty() ? 0.0 : double(hit) / double(rows.size()), truth == 0 ? 0.0 : double(hit) / double(truth)};
}

TEST(ActorExtraction, FindsEachMovingObjectAndItsGaussians) {
  const Extracted e = Extract();
  ASSERT_EQ(e.set.actors.size(), 2u) << "the truck and the car; the parked car and the wall stay scene";
  const Actor& truck = e.set.actors[0];
  const Actor& car = e.set.actors[1];
  const auto [tp, tr] = PrecisionRecall(truck.body_rows, e.street.part, Part::kTruck);
  const auto [cp, cr] = PrecisionRecall(car.body_rows, e.street.part, Part::kCar);
  const auto [gp, gr] = PrecisionRecall(truck.ghost_rows, e.street.part, Part::kTruckSmear);
  std::printf("truck body precision %.3f recall %.3f; car body %.3f / %.3f; truck ghost %.3f / %.3f\n", tp, tr, cp,
              cr, gp, gr);
  EXPECT_GE(tp, 0.99);
  EXPECT_GE(tr, 0.95);
  EXPECT_GE(cp, 0.99);
  EXPECT_GE(cr, 0.95);
  EXPECT_GE(gp, 0.99);
  EXPECT_GE(gr, 0.95) << "the smear where the truck stood must go with it";
  for (const Actor& a : e.set.actors) {
    for (const auto* rows : {&a.body_rows, &a.ghost_rows}) {
      for (uint32_t r : *rows) {
        ASSERT_NE(e.street.part[r], Part::kGround) << "the road under a path is not the actor's";
        ASSERT_NE(e.street.part[r], Part::kParked);
        ASSERT_NE(e.street.part[r], Part::kWall);
      }
    }
  }
  // The box and the trajectory: the truck's box is its size (plus margins), x along its motion,
  // and its path is 12 m along +x, then still.
  EXPECT_NEAR(2 * truck.half_extent_m.x(), 12.0 + 0.3, 0.2);
  EXPECT_NEAR(2 * truck.half_extent_m.y(), 2.5 + 0.3, 0.2);
  ASSERT_EQ(truck.trajectory.size(), size_t{kScans});
  const Eigen::Vector3d d = truck.trajectory[12].T_world_from_actor.translation() -
                            truck.trajectory[0].T_world_from_actor.translation();
  EXPECT_NEAR(d.x(), 12.0, 0.1);
  EXPECT_NEAR(d.y(), 0.0, 0.05);
  EXPECT_GT(truck.trajectory[0].T_world_from_actor.linear()(0, 0), 0.99) << "x forward along +x";
  EXPECT_LT(car.trajectory[0].T_world_from_actor.linear()(0, 0), -0.99) << "the car drives along -x";
  EXPECT_EQ(truck.start_time_us(), ScanTimeUs(0));
  EXPECT_EQ(truck.end_time_us(), ScanTimeUs(kScans - 1));
  EXPECT_EQ(truck.gaussians.size(), truck.body_rows.size());
}

// A scene without a field moves nothing: what stands in the box at the reference scan is the body
// (the truck where the static model has it, with the smear there), the rest of the path is ghost.
TEST(ActorExtraction, StaticSceneKeepsWhatStandsInTheBoxAsItsBody) {
  const Extracted e = Extract(/*static_scene=*/true);
  ASSERT_EQ(e.set.actors.size(), 2u);
  const Actor& truck = e.set.actors[0];
  const auto [tp, tr] = PrecisionRecall(truck.body_rows, e.street.part, Part::kTruck);
  EXPECT_GE(tr, 0.95);
  size_t smear_ghost = 0;
  for (uint32_t r : truck.ghost_rows) smear_ghost += e.street.part[r] == Part::kTruckSmear;
  EXPECT_GT(smear_ghost, 0u) << "the smear at scan 6 lies on the path";
  for (uint32_t r : truck.ghost_rows) ASSERT_NE(e.street.part[r], Part::kGround);
}

// A CPU render of `g` from the side of the street.
RenderOutput Render(const GaussianStore& g) {
  PinholeCamera cam;
  cam.width = 160;
  cam.height = 96;
  cam.fx = cam.fy = 70;
  cam.cx = 79.5;
  cam.cy = 47.5;
  cam.T_world_from_cam.linear() << 1, 0, 0, 0, 0, 1, 0, -1, 0;  // looking along +y, image down = -z
  cam.T_world_from_cam.translation() = Eigen::Vector3d(2, -22, 1.8);
  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(Backend::kCpu);
  EXPECT_TRUE(engine.ok());
  absl::StatusOr<std::unique_ptr<DeviceScene>> scene = (*engine)->Upload(g);
  EXPECT_TRUE(scene.ok()) << scene.status();
  RenderOptions options;
  RenderOutput out;
  EXPECT_TRUE((*engine)->Render(**scene, cam, options, &out).ok());
  return out;
}

TEST(ActorEdits, RemovalChangesOnlyTheActorsPixels) {
  const Extracted e = Extract();
  ASSERT_EQ(e.set.actors.size(), 2u);
  const int64_t t = ScanTimeUs(3);
  const GaussianStore now = e.street.At(t);
  const EditedScene removed = ApplyActorEdits(now, nullptr, e.set, {{ActorEdit::Kind::kRemove, 1, {}}}, t);
  EXPECT_EQ(removed.gaussians.size(),
            now.size() - e.set.actors[0].body_rows.size() - e.set.actors[0].ghost_rows.size());
  // The actor's own Gaussians alone say where its pixels are.
  GaussianStore own;
  std::vector<uint32_t> rows = e.set.actors[0].body_rows;
  rows.insert(rows.end(), e.set.actors[0].ghost_rows.begin(), e.set.actors[0].ghost_rows.end());
  AppendRows(now, rows.data(), rows.size(), &own);
  const RenderOutput before = Render(now), after = Render(removed.gaussians), mask = Render(own);
  int changed = 0, outside = 0;
  float worst_outside = 0;
  for (size_t p = 0; p < mask.alpha.size(); ++p) {
    float diff = 0;
    for (int c = 0; c < 3; ++c) diff = std::max(diff, std::abs(before.rgb[p * 3 + c] - after.rgb[p * 3 + c]));
    changed += diff > 0.1f;
    if (mask.alpha[p] < 1e-4f) {
      ++outside;
      worst_outside = std::max(worst_outside, diff);
    }
  }
  EXPECT_GT(changed, 200) << "the truck is in view and gone";
  EXPECT_GT(outside, 1000);
  EXPECT_LT(worst_outside, 1e-4f) << "a pixel the actor does not touch changed";
}

TEST(ActorEdits, MovedActorRendersAsItsGaussiansTransformed) {
  const Extracted e = Extract();
  ASSERT_EQ(e.set.actors.size(), 2u);
  const Actor& truck = e.set.actors[0];
  // Turned 90 degrees and put across the road in front of the camera.
  Eigen::Isometry3d P = Eigen::Isometry3d::Identity();
  P.linear() = Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  P.translation() = Eigen::Vector3d(3, 2, 1.8);
  const int64_t t = ScanTimeUs(15);
  const GaussianStore now = e.street.At(t);
  const std::vector<ActorEdit> edits = {{ActorEdit::Kind::kMove, 1, {{ScanTimeUs(0), P}, {ScanTimeUs(19), P}}}};
  ASSERT_TRUE(ValidateActorEdits(e.set, edits).ok());
  const EditedScene moved = ApplyActorEdits(now, nullptr, e.set, edits, t);

  // Expected, built directly: the scene without the truck's rows, plus the truck's Gaussians as
  // the scene had them at the reference scan, each mean carried by P T_ref^-1 (isotropic, SH 0:
  // nothing else changes).
  const GaussianStore at_ref = e.street.At(truck.reference_time_us);
  const Eigen::Isometry3d carry = P * PoseAt(truck.trajectory, truck.reference_time_us).inverse();
  std::vector<uint8_t> drop(now.size(), 0);
  for (uint32_t r : truck.body_rows) drop[r] = 1;
  for (uint32_t r : truck.ghost_rows) drop[r] = 1;
  std::vector<uint32_t> kept;
  for (uint32_t r = 0; r < now.size(); ++r) {
    if (!drop[r]) kept.push_back(r);
  }
  GaussianStore expected;
  AppendRows(now, kept.data(), kept.size(), &expected);
  const size_t first = expected.size();
  AppendRows(at_ref, truck.body_rows.data(), truck.body_rows.size(), &expected);
  for (size_t i = first; i < expected.size(); ++i) {
    const Eigen::Vector3d m = carry * Eigen::Vector3d(expected.means[i * 3], expected.means[i * 3 + 1],
                                                      expected.means[i * 3 + 2]);
    for (int a = 0; a < 3; ++a) expected.means[i * 3 + a] = static_cast<float>(m[a]);
  }
  const RenderOutput got = Render(moved.gaussians), want = Render(expected), before = Render(now);
  float worst = 0, moved_by = 0;
  for (size_t k = 0; k < got.rgb.size(); ++k) {
    worst = std::max(worst, std::abs(got.rgb[k] - want.rgb[k]));
    moved_by = std::max(moved_by, std::abs(got.rgb[k] - before.rgb[k]));
  }
  EXPECT_LT(worst, 2e-4f);
  EXPECT_GT(moved_by, 0.3f) << "the truck must be somewhere else";
  // An insert keeps the original and adds the copy.
  const EditedScene inserted =
      ApplyActorEdits(now, nullptr, e.set, {{ActorEdit::Kind::kInsert, 1, {{ScanTimeUs(0), P}}}}, t);
  EXPECT_EQ(inserted.gaussians.size(), now.size() + truck.body_rows.size());
}

TEST(ActorEdits, BadEditsAreRefused) {
  ActorSet set;
  set.actors.resize(1);
  set.actors[0].id = 1;
  const Eigen::Isometry3d I = Eigen::Isometry3d::Identity();
  auto expect_refused = [&](const std::vector<ActorEdit>& edits, const std::string& says) {
    const absl::Status s = ValidateActorEdits(set, edits);
    EXPECT_TRUE(absl::IsInvalidArgument(s)) << s;
    EXPECT_NE(s.message().find(says), std::string::npos) << s.message();
  };
  expect_refused({{ActorEdit::Kind::kRemove, 7, {}}}, "no such actor");
  Eigen::Isometry3d nan = I;
  nan.translation().x() = std::nan("");
  expect_refused({{ActorEdit::Kind::kMove, 1, {{0, nan}}}}, "not finite");
  Eigen::Isometry3d scaled = I;
  scaled.linear() *= 1.5;
  expect_refused({{ActorEdit::Kind::kInsert, 1, {{0, scaled}}}}, "unit quaternion");
  expect_refused({{ActorEdit::Kind::kMove, 1, {{10, I}, {10, I}}}}, "does not increase");
  expect_refused({{ActorEdit::Kind::kMove, 1, {}}}, "trajectory poses");
  expect_refused({{ActorEdit::Kind::kRemove, 1, {{0, I}}}}, "no trajectory");
  expect_refused({{ActorEdit::Kind::kRemove, 1, {}}, {ActorEdit::Kind::kMove, 1, {{0, I}}}}, "twice");
  expect_refused(std::vector<ActorEdit>(kMaxActorEdits + 1, {ActorEdit::Kind::kInsert, 1, {{0, I}}}), "at most");
  EXPECT_TRUE(ValidateActorEdits(set, {{ActorEdit::Kind::kInsert, 1, {{0, I}}}, {ActorEdit::Kind::kInsert, 1, {{0, I}}}})
                  .ok())
      << "two copies of one actor are fine";
}

TEST(ActorSetFiles, RoundTripAndRefuseAnotherScene) {
  const Extracted e = Extract();
  ASSERT_EQ(e.set.actors.size(), 2u);
  const std::string dir = streetsim::testing::ScratchDir("streetsim_actors", "files");
  ASSERT_TRUE(WriteGaussianPly(e.street.canonical, dir + "/scene.ply").ok());
  ActorSet set = e.set;
  set.sh_degree = 0;
  set.scene_checksum = *SceneChecksum(dir + "/scene.ply");
  ASSERT_TRUE(WriteActorSet(set, dir).ok());
  absl::StatusOr<ActorSet> back = ReadActorSet(dir);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->actors.size(), 2u);
  for (size_t a = 0; a < 2; ++a) {
    EXPECT_EQ(back->actors[a].id, set.actors[a].id);
    EXPECT_EQ(back->actors[a].body_rows, set.actors[a].body_rows);
    EXPECT_EQ(back->actors[a].ghost_rows, set.actors[a].ghost_rows);
    EXPECT_EQ(back->actors[a].gaussians.means, set.actors[a].gaussians.means);
    ASSERT_EQ(back->actors[a].trajectory.size(), set.actors[a].trajectory.size());
    EXPECT_TRUE(back->actors[a].trajectory[5].T_world_from_actor.isApprox(set.actors[a].trajectory[5].T_world_from_actor,
                                                                         1e-9));
  }
  // The scene trained again: refused, naming the file.
  GaussianStore other = e.street.canonical;
  other.opacity_logits[0] += 1;
  ASSERT_TRUE(WriteGaussianPly(other, dir + "/scene.ply").ok());
  absl::StatusOr<ActorSet> stale = ReadActorSet(dir);
  EXPECT_TRUE(absl::IsDataLoss(stale.status())) << stale.status();
  EXPECT_NE(stale.status().message().find("actors.json"), std::string::npos);
  // Damaged or from a newer schema.
  ASSERT_TRUE(WriteGaussianPly(e.street.canonical, dir + "/scene.ply").ok());
  std::ofstream(dir + "/actors.json") << "{\"schema\": 1, \"actors\": [";
  EXPECT_TRUE(absl::IsDataLoss(ReadActorSet(dir).status()));
  std::ofstream(dir + "/actors.json") << "{\"schema\": 2}";
  EXPECT_TRUE(absl::IsDataLoss(ReadActorSet(dir).status()));
  std::filesystem::remove(dir + "/actors.json");
  EXPECT_TRUE(absl::IsNotFound(ReadActorSet(dir).status()));
}

TEST(RigidGaussians, ShTurnsWithTheBody) {
  std::mt19937 rng(5);
  std::normal_distribution<double> n(0, 1);
  for (int trial = 0; trial < 5; ++trial) {
    const Eigen::Matrix3d R =
        Eigen::Quaterniond(n(rng), n(rng), n(rng), n(rng)).normalized().toRotationMatrix();
    GaussianStore g;
    g.sh_degree = 3;
    g.Resize(1);
    g.rotations[0] = 1;
    for (float& c : g.sh) c = static_cast<float>(n(rng));
    const GaussianStore original = g;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = R;
    TransformGaussians(T, &g);
    for (int k = 0; k < 20; ++k) {
      const Eigen::Vector3d d = Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
      const Eigen::Vector3d back = R.transpose() * d;
      double bd[16], bb[16];
      projection::ShBasis<double>(3, d.x(), d.y(), d.z(), bd);
      projection::ShBasis<double>(3, back.x(), back.y(), back.z(), bb);
      for (int c = 0; c < 3; ++c) {
        double now = 0, was = 0;
        for (int j = 0; j < 16; ++j) {
          now += bd[j] * g.sh[j * 3 + c];
          was += bb[j] * original.sh[j * 3 + c];
        }
        ASSERT_NEAR(now, was, 1e-4) << "trial " << trial << " direction " << k;
      }
    }
  }
}

}  // namespace
}  // namespace streetsim::actors
