// The serving form (scene/field/serving_form.h) against the exact field it was fitted to, and its
// cache (serving_form_io.h): every Gaussian's error bounded at times the fit never saw, the log's
// ends clamped, the static Gaussians untouched, and a cache that is stale, damaged or foreign
// never served.
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <tuple>

#include "gtest/gtest.h"
#include "scene/field/serving_form.h"
#include "scene/field/serving_form_io.h"
#include "scene/field/static_skip.h"
#include "tests/field/field_test_util.h"

namespace streetsim::field {
namespace {

namespace fs = std::filesystem;
constexpr int64_t kEndUs = 4'000'000;

// Every time plane varies smoothly in time (a few cycles over the log), so every Gaussian moves
// and changes colour; `band` adds testing::AddTimeVaryingBand's sharper band on top.
DeformationField MovingField(bool band) {
  absl::StatusOr<DeformationField> f = DeformationField::Create(testing::SmallConfig(), testing::TestAabb(), {0, kEndUs}, 5);
  EXPECT_TRUE(f.ok());
  const FieldLayout& L = f->layout();
  for (const PlaneInfo& pi : L.planes) {
    if (!PlaneHasTime(pi.plane)) continue;
    for (int v = 0; v < pi.height; ++v)
      for (int u = 0; u < pi.width; ++u)
        for (int k = 0; k < L.channels; ++k)
          f->mutable_params()[pi.offset + (size_t(v) * pi.width + u) * L.channels + k] =
              1.0f + 0.3f * std::sin(0.9f * v + 0.7f * u + k);
  }
  if (band) testing::AddTimeVaryingBand(&*f, 1);
  return std::move(*f);
}

GaussianStore Gaussians(size_t n) {
  GaussianStore g;
  g.sh_degree = 3;
  g.Resize(n);
  g.means = testing::RandomMeans<float>(n, 0, 11);
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> u(-1, 1);
  for (size_t i = 0; i < n; ++i) {
    g.rotations[i * 4] = 1;
    g.opacity_logits[i] = u(rng);
    for (int k = 0; k < 3; ++k) g.log_scales[i * 3 + k] = -3 + 0.2f * u(rng);
  }
  for (float& s : g.sh) s = 0.3f * u(rng);
  return g;
}

std::unique_ptr<ServingField> Exact(const DeformationField& f, const GaussianStore& g, bool skip, ThreadPool& pool) {
  StaticSkipOptions o;
  o.enabled = skip;
  absl::StatusOr<ServingField> s = ServingField::Create(f, g, o, pool);
  EXPECT_TRUE(s.ok()) << s.status();
  return std::make_unique<ServingField>(std::move(*s));
}

double PositionError(const GaussianStore& a, const GaussianStore& b, size_t i) {
  double d2 = 0;
  for (int k = 0; k < 3; ++k) d2 += std::pow(double(a.means[i * 3 + k]) - b.means[i * 3 + k], 2);
  return std::sqrt(d2);
}

TEST(ServingForm, EveryGaussianStaysWithinItsMeasuredBoundAtUnseenTimes) {
  ThreadPool pool(2);
  const DeformationField f = MovingField(false);
  const GaussianStore g = Gaussians(600);
  std::unique_ptr<ServingField> exact = Exact(f, g, false, pool);
  absl::StatusOr<std::unique_ptr<ServingForm>> form = ServingForm::Build(*exact, ServingFormOptions{}, pool);
  ASSERT_TRUE(form.ok()) << form.status();
  ASSERT_EQ((*form)->num_dynamic(), g.size());
  EXPECT_TRUE((*form)->models(FormGroup::kColour));
  EXPECT_FALSE((*form)->models(FormGroup::kRotation));  // S3Gaussian's field does not rotate
  const ServingFormError& e = (*form)->error();
  // The measured bound is small against the motion (the field moves Gaussians by decimetres).
  EXPECT_LT(e.max[0], 1e-2) << "position error at the check samples, m";
  EXPECT_LT(e.max[1], 2e-2) << "DC colour error at the check samples";
  EXPECT_TRUE((*form)->models(FormGroup::kShBands));
  std::mt19937 rng(9);
  std::uniform_int_distribution<int64_t> t(0, kEndUs);
  double largest_motion = 0;
  for (int s = 0; s < 40; ++s) {
    const int64_t time_us = t(rng);
    absl::StatusOr<const GaussianStore*> a = (*form)->At(time_us, pool);
    ASSERT_TRUE(a.ok());
    const GaussianStore served = **a;
    absl::StatusOr<const GaussianStore*> b = exact->At(time_us, pool);
    ASSERT_TRUE(b.ok());
    for (size_t r = 0; r < g.size(); ++r) {
      // Each Gaussian within its own bound from the check (x2: the check samples every quarter
      // segment, a random time falls anywhere) plus the quantisation floor.
      ASSERT_LE(PositionError(served, **b, r), 2 * (*form)->position_error_m()[r] + 1e-4) << "Gaussian " << r
                                                                                            << " at " << time_us;
      largest_motion = std::max(largest_motion, PositionError(**b, g, r));
    }
  }
  EXPECT_GT(largest_motion, 0.05) << "the field must move Gaussians for this test to mean anything";
}

TEST(ServingForm, BuildFitsAgainWithMoreSegmentsUntilWithinItsBound) {
  ThreadPool pool(2);
  const GaussianStore g = Gaussians(400);
  std::unique_ptr<ServingField> sharp = Exact(MovingField(true), g, false, pool);
  // Build fits again with more segments per cell of the field's time grid until the error is
  // within its bound.
  ServingFormOptions o;
  o.max_segments_per_cell = 8;
  absl::StatusOr<std::unique_ptr<ServingForm>> one = ServingForm::Fit(*sharp, 1, sharp->time_cells(), 4, pool);
  ASSERT_TRUE(one.ok());
  o.max_position_error_m = 0.5 * (*one)->error().position_p99_m;
  absl::StatusOr<std::unique_ptr<ServingForm>> c = ServingForm::Build(*sharp, o, pool);
  ASSERT_TRUE(c.ok());
  EXPECT_GT((*c)->segments(), sharp->time_cells());
  EXPECT_LE((*c)->error().position_p99_m, o.max_position_error_m);
}

// Knots on the field's time grid: the field's time features are linear between its nodes, so a
// piecewise-linear form with one segment per cell follows the field's kinks where a cubic B-spline
// with as many control points smooths them.
TEST(ServingForm, KnotsOnTheFieldsTimeGridFollowItsKinks) {
  ThreadPool pool(2);
  const GaussianStore g = Gaussians(400);
  std::unique_ptr<ServingField> sharp = Exact(MovingField(true), g, false, pool);
  const int cells = sharp->time_cells();
  EXPECT_EQ(cells, testing::SmallConfig().time_resolution - 1);
  // One segment per cell: the fit's error, not the int8 position residual's step, decides.
  absl::StatusOr<std::unique_ptr<ServingForm>> linear = ServingForm::Fit(*sharp, 1, cells, 4, pool);
  absl::StatusOr<std::unique_ptr<ServingForm>> cubic = ServingForm::Fit(*sharp, 3, cells - 2, 4, pool);
  ASSERT_TRUE(linear.ok() && cubic.ok());
  ASSERT_EQ((*linear)->control_points(), (*cubic)->control_points());
  EXPECT_LT((*linear)->error().position_p99_m, (*cubic)->error().position_p99_m);
}

TEST(ServingForm, StaticGaussiansAreUntouchedAndTheEndsClamp) {
  ThreadPool pool(2);
  absl::StatusOr<DeformationField> f = DeformationField::Create(testing::SmallConfig(), testing::TestAabb(), {0, kEndUs}, 7);
  ASSERT_TRUE(f.ok());
  testing::AddTimeVaryingBand(&*f, 1);  // only Gaussians in the band move
  const GaussianStore g = Gaussians(400);
  std::unique_ptr<ServingField> exact = Exact(*f, g, true, pool);
  ASSERT_GT(exact->num_dynamic(), 0u);
  ASSERT_LT(exact->num_dynamic(), g.size());
  absl::StatusOr<std::unique_ptr<ServingForm>> form = ServingForm::Build(*exact, ServingFormOptions{}, pool);
  ASSERT_TRUE(form.ok());
  EXPECT_EQ((*form)->num_dynamic(), exact->num_dynamic());
  std::vector<uint8_t> dynamic(g.size(), 0);
  for (uint32_t r : exact->dynamic_rows()) dynamic[r] = 1;
  const GaussianStore at_start = **(*form)->At(0, pool);
  const GaussianStore before = **(*form)->At(-5'000'000, pool);
  const GaussianStore exact_mid = **exact->At(kEndUs / 3, pool);
  const GaussianStore mid = **(*form)->At(kEndUs / 3, pool);
  const GaussianStore at_end = **(*form)->At(kEndUs, pool);
  const GaussianStore after = **(*form)->At(kEndUs + 1'000'000'000, pool);
  EXPECT_EQ(before.means, at_start.means);
  EXPECT_EQ(after.means, at_end.means);
  EXPECT_EQ(after.sh, at_end.sh);
  for (size_t i = 0; i < g.size(); ++i) {
    if (dynamic[i]) continue;
    for (int k = 0; k < 3; ++k) ASSERT_EQ(mid.means[i * 3 + k], exact_mid.means[i * 3 + k]) << i;
    for (int k = 0; k < 48; ++k) ASSERT_EQ(mid.sh[i * 48 + k], exact_mid.sh[i * 48 + k]) << i;
  }
  // Scales, rotations and opacities are not the field's: as trained, at every time.
  EXPECT_EQ(mid.log_scales, g.log_scales);
  EXPECT_EQ(mid.rotations, g.rotations);
  EXPECT_EQ(mid.opacity_logits, g.opacity_logits);
}

// The LiDAR's part of a time (GeometryAt) is the positions At gives, a tenth of the work; At of the
// same time then completes the colours without counting another evaluation. WritePlanesAt writes
// what At holds into an engine's planes.
TEST(ServingForm, GeometryAtAndWritePlanesAtAgreeWithAt) {
  ThreadPool pool(2);
  const DeformationField f = MovingField(false);
  const GaussianStore g = Gaussians(300);
  std::unique_ptr<ServingField> exact = Exact(f, g, false, pool);
  absl::StatusOr<std::unique_ptr<ServingForm>> built = ServingForm::Build(*exact, ServingFormOptions{}, pool);
  ASSERT_TRUE(built.ok()) << built.status();
  ServingForm& form = **built;
  const GaussianStore at_a = **form.At(kEndUs / 5, pool);
  const GaussianStore at_b = **form.At(kEndUs / 2, pool);
  ASSERT_NE(at_a.means, at_b.means);
  ASSERT_NE(at_a.sh, at_b.sh);

  const int64_t e0 = form.field_evaluations();
  const GaussianStore geometry_a = **form.GeometryAt(kEndUs / 5, pool);
  EXPECT_EQ(form.field_evaluations(), e0 + 1);
  EXPECT_EQ(geometry_a.means, at_a.means);
  EXPECT_EQ(geometry_a.sh, at_b.sh) << "the colours are the last full time's";
  EXPECT_EQ((**form.GeometryAt(kEndUs / 5, pool)).means, at_a.means);
  const GaussianStore completed = **form.At(kEndUs / 5, pool);
  EXPECT_EQ(form.field_evaluations(), e0 + 1) << "completing a time is not a new evaluation";
  EXPECT_EQ(completed.means, at_a.means);
  EXPECT_EQ(completed.sh, at_a.sh);
  EXPECT_EQ((**form.GeometryAt(kEndUs / 5, pool)).sh, at_a.sh);  // already whole: nothing to do
  EXPECT_EQ(form.field_evaluations(), e0 + 1);

  // Planes laid out as the cpu engine's (render/cpu/scene_soa.h), filled from the start's store.
  const GaussianStore start = **form.At(0, pool);
  const size_t n = start.size(), plane = (n + 15) / 16 * 16;
  std::vector<std::vector<float>> scalar(11, std::vector<float>(n));
  std::vector<float> sh(48 * plane + 16);
  float* sh0 = sh.data();
  while (reinterpret_cast<uintptr_t>(sh0) % 64 != 0) ++sh0;
  ScenePlanes p;
  p.n = n;
  p.sh_degree = 3;
  p.sh = sh0;
  p.sh_plane = plane;
  for (int c = 0; c < 3; ++c) p.mean[c] = scalar[c].data(), p.log_scale[c] = scalar[3 + c].data();
  for (int c = 0; c < 4; ++c) p.rotation[c] = scalar[6 + c].data();
  p.opacity_logit = scalar[10].data();
  for (size_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) p.mean[c][i] = start.means[i * 3 + c];
    for (int kc = 0; kc < 48; ++kc) p.sh[kc * plane + i] = start.sh[i * 48 + kc];
  }
  const int64_t e1 = form.field_evaluations();
  ASSERT_TRUE(form.WritePlanesAt(kEndUs / 2, p, pool).ok());
  EXPECT_EQ(form.field_evaluations(), e1 + 1);
  EXPECT_EQ((**form.GeometryAt(kEndUs / 2, pool)).means, at_b.means) << "written in the planes' pass";
  EXPECT_EQ(form.field_evaluations(), e1 + 1);
  EXPECT_EQ((**form.At(kEndUs / 2, pool)).sh, at_b.sh);
  for (size_t i = 0; i < n; ++i) {
    for (int c = 0; c < 3; ++c) ASSERT_NEAR(p.mean[c][i], at_b.means[i * 3 + c], 1e-5) << i;
    for (int kc = 0; kc < 48; ++kc) ASSERT_NEAR(p.sh[kc * plane + i], at_b.sh[i * 48 + kc], 1e-5) << i << " " << kc;
  }
  ScenePlanes other = p;
  other.n = n - 1;
  EXPECT_EQ(form.WritePlanesAt(0, other, pool).code(), absl::StatusCode::kInvalidArgument);
  other = p;
  other.sh_degree = 1;
  EXPECT_EQ(form.WritePlanesAt(0, other, pool).code(), absl::StatusCode::kInvalidArgument);
}

TEST(ServingForm, BadOptionsAreRefused) {
  ThreadPool pool(1);
  const GaussianStore g = Gaussians(10);
  std::unique_ptr<ServingField> exact = Exact(MovingField(false), g, false, pool);
  for (auto [degree, per_cell, max_per_cell, samples] :
       {std::tuple{2, 1, 4, 4}, std::tuple{1, 0, 4, 4}, std::tuple{1, 5, 4, 4}, std::tuple{1, 1, 65, 4},
        std::tuple{3, 1, 4, 1}, std::tuple{3, 1, 4, 65}}) {
    ServingFormOptions o;
    o.degree = degree;
    o.segments_per_cell = per_cell;
    o.max_segments_per_cell = max_per_cell;
    o.samples_per_segment = samples;
    EXPECT_EQ(ServingForm::Build(*exact, o, pool).status().code(), absl::StatusCode::kInvalidArgument)
        << degree << " " << per_cell << " " << max_per_cell << " " << samples;
  }
  ServingFormOptions o;
  o.max_position_error_m = std::nan("");
  EXPECT_EQ(ServingForm::Build(*exact, o, pool).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ServingForm::Fit(*exact, 1, 0, 4, pool).status().code(), absl::StatusCode::kInvalidArgument);
}

class ServingFormCache : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("serving_form_test_" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    cache_ = (dir_ / kServingFormFileName).string();
  }
  void TearDown() override {
    fs::permissions(dir_, fs::perms::owner_all);
    fs::remove_all(dir_);
  }
  absl::StatusOr<CachedServingForm> Load(uint64_t key) {
    return LoadOrBuildServingForm(
        cache_, key,
        [&]() -> absl::StatusOr<std::unique_ptr<ServedScene>> {
          ++builds_;
          return std::unique_ptr<ServedScene>(Exact(field_, g_, true, pool_));
        },
        ServingFormOptions{}, pool_);
  }
  std::string Bytes() {
    std::ifstream in(cache_, std::ios::binary);
    return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  }
  void Write(const std::string& bytes) { std::ofstream(cache_, std::ios::binary | std::ios::trunc) << bytes; }

  ThreadPool pool_{2};
  DeformationField field_ = MovingField(true);
  GaussianStore g_ = Gaussians(300);
  fs::path dir_;
  std::string cache_;
  int builds_ = 0;
};

TEST_F(ServingFormCache, BuildsOnceThenServesTheSameFormFromTheCache) {
  absl::StatusOr<CachedServingForm> first = Load(42);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_FALSE(first->from_cache);
  EXPECT_TRUE(fs::exists(cache_));
  absl::StatusOr<CachedServingForm> second = Load(42);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_TRUE(second->from_cache);
  EXPECT_EQ(builds_, 1);
  for (int64_t t : {int64_t{0}, kEndUs / 7, kEndUs / 2, kEndUs}) {
    const GaussianStore a = **first->form->At(t, pool_);
    const GaussianStore b = **second->form->At(t, pool_);
    EXPECT_EQ(a.means, b.means);
    EXPECT_EQ(a.sh, b.sh);
    EXPECT_EQ(a.opacity_logits, b.opacity_logits);
  }
  EXPECT_EQ(first->form->error().max, second->form->error().max);
}

TEST_F(ServingFormCache, StaleDamagedAndForeignCachesAreRebuiltNamingThePath) {
  ASSERT_TRUE(Load(42).ok());
  const std::string good = Bytes();
  // Another key: the scene's files changed since the cache was written.
  absl::StatusOr<CachedServingForm> stale = Load(43);
  ASSERT_TRUE(stale.ok());
  EXPECT_FALSE(stale->from_cache);
  EXPECT_NE(stale->note.find(cache_), std::string::npos) << stale->note;
  EXPECT_NE(stale->note.find("stale"), std::string::npos) << stale->note;
  std::string flipped = good;
  flipped[flipped.size() / 2] ^= 0x10;
  std::string future = good;
  future[8] = 9;  // the version after the magic
  for (const std::string& bad : {good.substr(0, good.size() / 3), flipped, future, std::string("not a form at all"),
                                 std::string()}) {
    Write(bad);
    const int before = builds_;
    absl::StatusOr<CachedServingForm> r = Load(42);
    ASSERT_TRUE(r.ok()) << r.status();
    EXPECT_FALSE(r->from_cache);
    EXPECT_EQ(builds_, before + 1);
    EXPECT_NE(r->note.find(cache_), std::string::npos) << r->note;
    EXPECT_EQ(Bytes(), good) << "the rebuilt cache is the same form";
  }
  // The decoder alone: DataLoss naming the path for damage, FailedPrecondition for a stale key.
  EXPECT_EQ(DecodeServingForm(flipped, 42, "p").status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(DecodeServingForm(good, 7, "p").status().code(), absl::StatusCode::kFailedPrecondition);
  absl::StatusOr<std::unique_ptr<ServingForm>> decoded = DecodeServingForm(good, 42, "p");
  EXPECT_TRUE(decoded.ok()) << decoded.status();
}

TEST_F(ServingFormCache, ACacheThatCannotBeWrittenServesFromMemory) {
  // Its directory is a regular file: no write succeeds there, for root either.
  std::ofstream((dir_ / "plain").string()) << "x";
  cache_ = (dir_ / "plain" / kServingFormFileName).string();
  absl::StatusOr<CachedServingForm> r = Load(42);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_FALSE(r->from_cache);
  EXPECT_NE(r->note.find("served from memory"), std::string::npos) << r->note;
  EXPECT_NE(r->note.find(cache_), std::string::npos) << r->note;
  EXPECT_GT(r->form->num_dynamic(), 0u);
}

TEST(ServingFormKey, FollowsTheFilesBytesAndTheOptions) {
  const fs::path dir = fs::temp_directory_path() / ("serving_form_key_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const std::string a = (dir / "scene.ply").string(), b = (dir / "field.bin").string(), c = (dir / "field_ext.bin").string();
  std::ofstream(a) << "gaussians";
  std::ofstream(b) << "field";
  const uint64_t k0 = *ServingFormSourceKey({a, b, c}, {}, {});
  EXPECT_EQ(*ServingFormSourceKey({a, b, c}, {}, {}), k0);
  std::ofstream(b) << "field retrained";
  const uint64_t k1 = *ServingFormSourceKey({a, b, c}, {}, {});
  EXPECT_NE(k1, k0);
  std::ofstream(c) << "extension";
  EXPECT_NE(*ServingFormSourceKey({a, b, c}, {}, {}), k1);
  ServingFormOptions more;
  more.segments_per_cell = 2;
  EXPECT_NE(*ServingFormSourceKey({a, b, c}, more, {}), *ServingFormSourceKey({a, b, c}, {}, {}));
  ServingFormOptions looser;
  looser.max_position_error_m = 0.01;
  EXPECT_NE(*ServingFormSourceKey({a, b, c}, looser, {}), *ServingFormSourceKey({a, b, c}, {}, {}));
  StaticSkipOptions skip;
  skip.motion_threshold_m = 0.02;
  EXPECT_NE(*ServingFormSourceKey({a, b, c}, {}, skip), *ServingFormSourceKey({a, b, c}, {}, {}));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace streetsim::field
