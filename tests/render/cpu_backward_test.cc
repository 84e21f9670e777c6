// cpu backward kernels: the vectorised projection backward (project_backward_simd.inc) against the
// scalar reference (ProjectGaussianBackward one Gaussian at a time) on the same inputs, on random
// scenes of every SH degree and on a street scene with real blend-backward gradients.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <random>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "render/cpu/binning.h"
#include "render/params_view.h"
#include "render/cpu/blend.h"
#include "render/cpu/blend_backward.h"
#include "render/cpu/cpu_engine.h"
#include "render/cpu/project.h"
#include "render/cpu/project_bwd.h"
#include "render/cpu/simd_dispatch.h"
#include "scene/gaussians/synthetic_street.h"
#include "tests/common/grad_check_scene.h"
#include "tests/common/needle_splats.h"
#include "tests/common/params_view.h"

namespace streetsim {
namespace {

struct Group {
  const char* name;
  std::vector<float> GaussianGrads::*grads;
};
const Group kGroups[] = {{"means", &GaussianGrads::means},
                         {"log_scales", &GaussianGrads::log_scales},
                         {"rotations", &GaussianGrads::rotations},
                         {"opacity_logits", &GaussianGrads::opacity_logits},
                         {"sh", &GaussianGrads::sh},
                         {"means2d", &GaussianGrads::means2d}};

// 99.9th percentile over a group of |a - b| / (|b| + 1e-3 rms(b)): relative error where a value
// is not tiny against its group, absolute (in units of the group's scale) where it is.
double RelErrorP999(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  double ss = 0;
  for (float v : b) ss += double(v) * v;
  const double floor = 1e-3 * std::sqrt(ss / std::max<size_t>(1, b.size())) + 1e-30;
  std::vector<double> e(b.size());
  for (size_t i = 0; i < b.size(); ++i) e[i] = std::abs(double(a[i]) - b[i]) / (std::abs(double(b[i])) + floor);
  if (e.empty()) return 0;
  const size_t k = std::min(e.size() - 1, static_cast<size_t>(0.999 * e.size()));
  std::nth_element(e.begin(), e.begin() + k, e.end());
  return e[k];
}

// The vectorised path, the scalar float path and the scalar double path on the same projected
// frame and splat gradients. Flat Gaussians make some gradients (rotations through the
// quaternion normalisation) ill-conditioned, so the float paths are judged against double: the
// vectorised one may not be much worse than the scalar one. Invisible Gaussians must be exactly 0.
void ExpectSimdMatchesScalar(const GaussianStore& store, const cpu::SceneSoa& soa, const PinholeCamera& camera,
                             const cpu::Frame<float>& frame, const std::vector<float>& splat_grads,
                             const char* what) {
  ThreadPool pool(2);
  const auto cam = cpu::MakeCameraParams<float>(camera);
  GaussianGrads simd, ref, ref_d;
  cpu::ProjectBackwardSoa(pool, soa, cam, frame, splat_grads, &simd);
  cpu::ProjectBackwardSoaScalar(pool, soa, cam, frame, splat_grads, &ref);
  cpu::Frame<double> frame_d;
  frame_d.visible = frame.visible;
  frame_d.visible_ids = frame.visible_ids;
  const std::vector<double> splat_grads_d(splat_grads.begin(), splat_grads.end());
  cpu::ProjectBackwardStore<double>(pool, store, cpu::MakeCameraParams<double>(camera), frame_d, splat_grads_d, &ref_d);
  for (const Group& g : kGroups) {
    const double e = RelErrorP999(simd.*(g.grads), ref.*(g.grads));
    const double e_simd = RelErrorP999(simd.*(g.grads), ref_d.*(g.grads));
    const double e_scalar = RelErrorP999(ref.*(g.grads), ref_d.*(g.grads));
    std::printf("%s %-15s p99.9 rel. error: simd vs scalar %.2e, vs double: simd %.2e, scalar %.2e\n", what,
                g.name, e, e_simd, e_scalar);
    EXPECT_LT(e_simd, 2 * e_scalar + 1e-5) << what << " " << g.name;
    EXPECT_LT(e_simd, 5e-3) << what << " " << g.name;
  }
  size_t radius_diff = 0, nonzero_invisible = 0;
  const int K = (soa.sh_degree + 1) * (soa.sh_degree + 1);
  for (size_t i = 0; i < soa.n; ++i) {
    radius_diff += std::abs(simd.radii[i] - ref.radii[i]) > 1.0f + 1e-5f * std::abs(ref.radii[i]);
    if (!frame.visible[i]) {
      nonzero_invisible += simd.radii[i] != 0 || simd.opacity_logits[i] != 0 || simd.means[i * 3] != 0 ||
                           simd.sh[i * K * 3 + K * 3 - 1] != 0;
    }
  }
  // ceil(3 sqrt(lambda_max)) may flip where the argument is within rounding of an integer, and a
  // needle's radius of 1e6 px differs in its last float bits.
  EXPECT_LE(radius_diff, soa.n / 1000 + 1) << what;
  EXPECT_EQ(nonzero_invisible, 0u) << what;
}

cpu::Frame<float> Project(ThreadPool& pool, const cpu::SceneSoa& soa, const projection::CameraParams<float>& cam) {
  cpu::Frame<float> f;
  f.width = cam.width;
  f.height = cam.height;
  f.tiles_x = cam.tiles_x;
  f.tiles_y = cam.tiles_y;
  cpu::ProjectGaussiansSimd(pool, soa, cam, &f);
  return f;
}

TEST(CpuBackward, VectorisedProjectionBackwardMatchesReferenceOnRandomScenes) {
  ThreadPool pool(2);
  for (int degree = 0; degree <= 3; ++degree) {
    // 3001: not a multiple of the chunk; random scenes put Gaussians beside and behind the view.
    gradcheck::Scene s = gradcheck::RandomScene(40 + degree, 3001, degree, 160, 96);
    std::mt19937 rng(degree);
    std::uniform_real_distribution<float> u(-1, 1);
    for (size_t i = 0; i < s.store.size(); i += 3) s.store.means[i * 3 + 2] -= 6.0f * std::abs(u(rng));
    const cpu::SceneSoa soa = cpu::SceneSoa::FromStore(s.store);
    const cpu::Frame<float> f = Project(pool, soa, cpu::MakeCameraParams<float>(s.cam));
    ASSERT_GT(f.visible_ids.size(), 1000u);
    ASSERT_LT(f.visible_ids.size(), soa.n);
    // Random splat gradients everywhere (invisible ones must still come out zero), with scales
    // spread over decades like real ones.
    std::vector<float> g(soa.n * cpu::kSplatGradSize);
    for (float& v : g) v = u(rng) * std::pow(10.0f, 2.0f * u(rng));
    const std::string what = "degree " + std::to_string(degree);
    ExpectSimdMatchesScalar(s.store, soa, s.cam, f, g, what.c_str());
  }
}

// A street frame rendered with keep_for_backward (cpu internals) and the splat gradients of an
// L2 loss against a grey image.
struct StreetFrame {
  GaussianStore store;
  PinholeCamera camera;
  cpu::SceneSoa soa;
  cpu::Frame<float> frame;
  std::vector<float> rgb, d_rgb, d_depth, splat_grads;
  cpu::BlendBackwardArgs<float> bargs;
};

std::unique_ptr<StreetFrame> MakeStreetFrame(ThreadPool& pool) {
  auto sf = std::make_unique<StreetFrame>();
  sf->store = MakeSyntheticStreet({.num_gaussians = 40'000, .seed = 5, .sh_degree = 3});
  PinholeCamera& camera = sf->camera;
  camera.width = 324;
  camera.height = 210;
  camera.fx = camera.fy = 188.2;
  camera.cx = 161.5;
  camera.cy = 104.5;
  camera.T_world_from_cam = StreetCameraPose(12.0);
  sf->soa = cpu::SceneSoa::FromStore(sf->store);
  cpu::Frame<float>& f = sf->frame;
  f = Project(pool, sf->soa, cpu::MakeCameraParams<float>(camera));
  cpu::SortByDepth(&f);
  cpu::BinTiles(pool, &f);
  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  sf->rgb.resize(pixels * 3);
  std::vector<float> depth(pixels);
  f.final_T.resize(pixels);
  f.n_contrib.resize(pixels);
  cpu::BlendArgs<float> args;
  args.frame = &f;
  args.rgb = sf->rgb.data();
  args.depth = depth.data();
  args.final_T = f.final_T.data();
  args.n_contrib = f.n_contrib.data();
  cpu::BlendSimd(pool, args);
  sf->d_rgb.resize(pixels * 3);
  sf->d_depth.resize(pixels);
  for (size_t i = 0; i < pixels * 3; ++i) sf->d_rgb[i] = 2.0f * (sf->rgb[i] - 0.4f) / pixels;
  for (size_t i = 0; i < pixels; ++i) sf->d_depth[i] = 1e-3f * (depth[i] - 10.0f) / pixels;
  sf->bargs.frame = &f;
  sf->bargs.background[1] = 0.3f;
  sf->bargs.d_rgb = sf->d_rgb.data();
  sf->bargs.d_depth = sf->d_depth.data();
  cpu::BlendBackwardScratch<float> scratch;
  cpu::BlendBackwardSimd(pool, sf->bargs, false, &scratch, &sf->splat_grads);
  return sf;
}

TEST(CpuBackward, VectorisedProjectionBackwardMatchesReferenceOnStreetScene) {
  ThreadPool pool(2);
  const auto sf = MakeStreetFrame(pool);
  ASSERT_GT(sf->frame.visible_ids.size(), 5000u);
  ExpectSimdMatchesScalar(sf->store, sf->soa, sf->camera, sf->frame, sf->splat_grads, "street");
}

// Needle splats: one axis up to 160 km long, the others millimetres (what an unbounded decoder
// Δlog-scale produced in training). Their 2D covariance is near rank one, so cxx cyy - cxy^2
// cancels in float; the projection must compute its determinant without that cancellation, so
// that every visible splat's gradients are finite and close to double's.
TEST(CpuBackward, NeedleSplatsGiveFiniteGradients) {
  ThreadPool pool(2);
  gradcheck::Scene s = gradcheck::RandomScene(77, 4000, 3, 160, 96);
  std::mt19937 rng(77);
  testing::MakeNeedles(8.0f, 4.0f, rng, &s.store);
  std::uniform_real_distribution<float> u(-1, 1);
  const cpu::SceneSoa soa = cpu::SceneSoa::FromStore(s.store);
  const auto cam = cpu::MakeCameraParams<float>(s.cam);
  const cpu::Frame<float> f = Project(pool, soa, cam);
  ASSERT_GT(f.visible_ids.size(), 1000u);
  std::vector<float> g(soa.n * cpu::kSplatGradSize);
  for (float& v : g) v = u(rng);
  GaussianGrads simd, scalar;
  cpu::ProjectBackwardSoa(pool, soa, cam, f, g, &simd);
  cpu::ProjectBackwardSoaScalar(pool, soa, cam, f, g, &scalar);
  for (const Group& grp : kGroups) {
    for (const GaussianGrads* out : {&simd, &scalar}) {
      const std::vector<float>& v = out->*(grp.grads);
      const size_t bad = std::count_if(v.begin(), v.end(), [](float x) { return !std::isfinite(x); });
      EXPECT_EQ(bad, 0u) << grp.name << (out == &simd ? " (vectorised)" : " (scalar)");
    }
  }
  // Every visible splat's conic is finite, and bounded by the low-pass filter (cov >= 0.3 I).
  size_t bad_conic = 0;
  for (uint32_t i : f.visible_ids) {
    const auto& b = f.splats[i];
    bad_conic += !(std::isfinite(b.a) && std::isfinite(b.b) && std::isfinite(b.c) && b.a > 0 && b.c > 0 &&
                   b.a <= 1 / 0.3f * 1.001f && b.c <= 1 / 0.3f * 1.001f && b.det_conic > 0);
  }
  EXPECT_EQ(bad_conic, 0u) << "of " << f.visible_ids.size();
  ExpectSimdMatchesScalar(s.store, soa, s.cam, f, g, "needles");
}

double RelL2(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  double num = 0, den = 0;
  for (size_t i = 0; i < std::min(a.size(), b.size()); ++i) {
    num += std::pow(double(a[i]) - b[i], 2);
    den += std::pow(double(b[i]), 2);
  }
  return std::sqrt(num / std::max(den, 1e-300));
}

// Each kernel is built for AVX2 and AVX-512 and the machine picks one; the tests above run the
// picked one. Here the AVX2 builds (hand-written mask and transpose paths differ) are run
// directly against the dispatched ones, on a machine with AVX-512 a real comparison.
TEST(CpuBackward, Avx2AndDispatchedBuildsAgree) {
  ThreadPool pool(2);
  const auto sf = MakeStreetFrame(pool);
  const cpu::Frame<float>& f = sf->frame;
  const int64_t tiles = static_cast<int64_t>(f.tiles_x) * f.tiles_y;
  const size_t pixels = static_cast<size_t>(f.width) * f.height;
  std::printf("dispatched build: %s\n", cpu::BlendSimdIsa());
  // Forward.
  std::vector<float> rgb(pixels * 3), final_T(pixels);
  std::vector<uint32_t> n_contrib(pixels);
  cpu::BlendArgs<float> args;
  args.frame = &f;
  args.rgb = rgb.data();
  args.final_T = final_T.data();
  args.n_contrib = n_contrib.data();
  cpu::simd_avx2::BlendTiles(args, 0, tiles);
  EXPECT_LT(RelL2(rgb, sf->rgb), 1e-6);
  EXPECT_LT(RelL2(final_T, f.final_T), 1e-6);
  size_t contrib_diff = 0;
  for (size_t i = 0; i < pixels; ++i) contrib_diff += n_contrib[i] != f.n_contrib[i];
  EXPECT_LE(contrib_diff, pixels / 1000);
  // Blend backward.
  std::vector<float> acc(f.splats.size() * cpu::kSplatGradSize, 0.0f);
  cpu::bwd_avx2::BlendBackwardTiles(sf->bargs, 0, tiles, acc.data(), nullptr);
  const double e_blend = RelL2(acc, sf->splat_grads);
  std::printf("blend backward avx2 vs dispatched rel. L2 %.2e\n", e_blend);
  EXPECT_LT(e_blend, 1e-5);
  // Projection backward.
  const auto cam = cpu::MakeCameraParams<float>(sf->camera);
  GaussianGrads ref, avx2;
  cpu::ProjectBackwardSoa(pool, sf->soa, cam, f, sf->splat_grads, &ref);
  avx2 = ref;  // sized; every element is overwritten
  for (auto* v : {&avx2.means, &avx2.log_scales, &avx2.rotations, &avx2.opacity_logits, &avx2.sh, &avx2.means2d,
                  &avx2.radii}) {
    std::fill(v->begin(), v->end(), -1.0f);
  }
  cpu::pbwd_avx2::ProjectBackwardRange(sf->soa, cam, f.visible.data(), sf->splat_grads.data(), 0,
                                       static_cast<int64_t>(sf->soa.n), &avx2);
  for (const Group& g : kGroups) {
    const double e = RelL2(avx2.*(g.grads), ref.*(g.grads));
    std::printf("projection backward avx2 vs dispatched %-15s rel. L2 %.2e\n", g.name, e);
    EXPECT_LT(e, 1e-5) << g.name;
  }
  EXPECT_EQ(avx2.radii, ref.radii);
}

// The engine keeps its backward scratch between calls (the merge leaves the per-thread arrays
// zeroed for the next one): a second backward of the same frame gives the same gradients, and a
// backward after a scene of another size still starts from zeros.
TEST(CpuBackward, RepeatedBackwardCallsGiveTheSameGradients) {
  auto engine = CreateCpuEngine({.num_threads = 2});
  gradcheck::Scene small = gradcheck::RandomScene(8, 500, 3, 96, 64);
  gradcheck::Scene large = gradcheck::RandomScene(9, 900, 3, 96, 64);
  auto run = [&](const gradcheck::Scene& s, bool deterministic) {
    auto scene = engine->Upload(s.store);
    EXPECT_TRUE(scene.ok());
    RenderOptions opt;
    opt.keep_for_backward = true;
    RenderOutput out;
    EXPECT_TRUE(engine->Render(**scene, s.cam, opt, &out).ok());
    const std::vector<float> g(s.w_rgb.begin(), s.w_rgb.end());
    GaussianGrads grads;
    BackwardOptions bo;
    bo.deterministic = deterministic;
    EXPECT_TRUE(engine->RenderBackward(**scene, {g.data()}, bo, &grads).ok());
    return grads;
  };
  const GaussianGrads first = run(small, false);
  const GaussianGrads again = run(small, false);
  const GaussianGrads fixed_order = run(small, true);
  (void)run(large, false);
  const GaussianGrads after_resize = run(small, false);
  for (const Group& g : kGroups) {
    EXPECT_LT(RelL2(again.*(g.grads), first.*(g.grads)), 1e-5) << g.name;
    EXPECT_LT(RelL2(fixed_order.*(g.grads), first.*(g.grads)), 1e-5) << g.name;
    EXPECT_LT(RelL2(after_resize.*(g.grads), first.*(g.grads)), 1e-5) << g.name;
  }
}

// The 160x96 street view of the update tests below.
PinholeCamera UpdateTestCamera() {
  PinholeCamera camera;
  camera.width = 160;
  camera.height = 96;
  camera.fx = camera.fy = 120;
  camera.cx = 79.5;
  camera.cy = 47.5;
  camera.T_world_from_cam = StreetCameraPose(4.0);
  return camera;
}

// Training uploads parameters through UpdateSceneParams (the trainer's layout: SH stride 16 at any
// active degree; the SoA copy's SH is transposed 8 x 8 in registers where it can): the frame must
// be the one a plain Upload of the same parameters gives, bit for bit, and a non-finite value
// anywhere must be refused.
TEST(CpuBackward, UpdateSceneParamsRendersLikeUpload) {
  const GaussianStore full = MakeSyntheticStreet({.num_gaussians = 1'003, .seed = 4, .sh_degree = 3});
  const PinholeCamera camera = UpdateTestCamera();
  auto engine = CreateCpuEngine({.num_threads = 2});
  for (int degree : {1, 3}) {
    GaussianParamsView v = testing::FullDegreeParamsView(full, degree);
    std::unique_ptr<DeviceScene> updated;
    ASSERT_TRUE(engine->UpdateSceneParams(v, &updated).ok());
    ASSERT_TRUE(engine->UpdateSceneParams(v, &updated).ok());  // in place the second time
    const GaussianStore store = testing::TruncatedToDegree(full, degree);
    auto uploaded = engine->Upload(store);
    ASSERT_TRUE(uploaded.ok());
    RenderOutput a, b;
    ASSERT_TRUE(engine->Render(*updated, camera, {}, &a).ok());
    ASSERT_TRUE(engine->Render(**uploaded, camera, {}, &b).ok());
    EXPECT_GT(a.stats.num_visible, 100u);
    EXPECT_EQ(a.rgb, b.rgb) << "degree " << degree;
    // A nan in a coefficient the register path moves (block 0) and in one the scalar tail moves.
    for (size_t bad_index : {size_t{5 * 48 + 7}, size_t{1'001 * 48 + 2}}) {
      std::vector<float> sh = full.sh;
      sh[bad_index] = std::nanf("");
      v.sh = sh.data();
      const absl::Status st = engine->UpdateSceneParams(v, &updated);
      EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << bad_index;
      // The message names the Gaussian and the coefficient, so that a diverging run says where.
      EXPECT_THAT(std::string(st.message()),
                  ::testing::HasSubstr(absl::StrCat("Gaussian ", bad_index / 48, ": SH[", bad_index % 48, "]")));
      v.sh = full.sh.data();
    }
    std::vector<float> rotations = full.rotations;
    std::fill_n(rotations.begin() + 4 * 17, 4, 0.0f);
    v.rotations = rotations.data();
    const absl::Status st = engine->UpdateSceneParams(v, &updated);
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(st.message()), ::testing::HasSubstr("Gaussian 17: rotation = (0, 0, 0, 0)"));
    v.rotations = full.rotations.data();
  }
}

// The frame of `store` uploaded whole.
std::vector<float> UploadedRgb(Engine& engine, const GaussianStore& store) {
  auto scene = engine.Upload(store);
  EXPECT_TRUE(scene.ok()) << scene.status();
  RenderOutput out;
  if (scene.ok()) {
    EXPECT_TRUE(engine.Render(**scene, UpdateTestCamera(), {}, &out).ok());
  }
  return out.rgb;
}

// The frame after a full update to `before` and a row update (`change`) from the view of `after`;
// empty when the row update is refused, `*status` then says why.
std::vector<float> RowUpdatedRgb(Engine& engine, const GaussianStore& before, const GaussianStore& after,
                                 const ParamsChange& change, absl::Status* status = nullptr) {
  std::unique_ptr<DeviceScene> scene;
  EXPECT_TRUE(engine.UpdateSceneParams(ParamsViewOf(before), &scene).ok());
  const absl::Status st = engine.UpdateSceneRows(ParamsViewOf(after), change, &scene);
  if (status != nullptr) *status = st;
  if (!st.ok()) return {};
  RenderOutput out;
  EXPECT_TRUE(engine.Render(*scene, UpdateTestCamera(), {}, &out).ok());
  return out.rgb;
}

ParamsChange ChangeOf(const std::vector<uint32_t>& rows, int sh_coeffs) {
  ParamsChange change;
  change.rows = rows.data();
  change.num_rows = rows.size();
  change.sh_coeffs = sh_coeffs;
  return change;
}

// Serving updates only the moving Gaussians' changed values (UpdateSceneRows): after a full
// update at one time and a row update to another, the frame is the one a plain Upload of the
// second time gives, bit for bit; a non-finite changed value or a row out of range is refused.
TEST(CpuBackward, UpdateSceneRowsRendersLikeUploadOfTheNewTime) {
  const GaussianStore before = MakeSyntheticStreet({.num_gaussians = 1'003, .seed = 5, .sh_degree = 3});
  GaussianStore after = before;
  std::vector<uint32_t> rows;
  for (uint32_t i = 3; i < before.size(); i += 7) {
    rows.push_back(i);
    for (int k = 0; k < 3; ++k) after.means[i * 3 + k] += 0.05f * (k + 1);
    for (int k = 0; k < 3; ++k) after.sh[i * 48 + k] += 0.2f;  // DC only
    after.opacity_logits[i] += 0.5f;
  }
  ParamsChange change = ChangeOf(rows, 1);
  change.means = change.opacity = true;
  auto engine = CreateCpuEngine({.num_threads = 2});
  const std::vector<float> updated = RowUpdatedRgb(*engine, before, after, change);
  EXPECT_EQ(updated, UploadedRgb(*engine, after));
  EXPECT_NE(updated, UploadedRgb(*engine, before)) << "the change must show";
  GaussianStore bad = after;
  bad.means[rows[4] * 3 + 1] = std::nanf("");
  absl::Status st;
  RowUpdatedRgb(*engine, before, bad, change, &st);
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
  const std::vector<uint32_t> out_of_range = {5, static_cast<uint32_t>(after.size())};
  ParamsChange past_end = ChangeOf(out_of_range, 1);
  past_end.means = true;
  RowUpdatedRgb(*engine, before, after, past_end, &st);
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
}

// A dynamic scene moves runs of consecutive Gaussians: those rows take the tiled transpose of the
// SH into the engine's plane-major arrays (render/cpu/scene_soa.cc), streamed from a cache line's
// start, the others row by row.
// Both must land where a plain Upload puts them, and a NaN inside a tile is refused.
TEST(CpuBackward, UpdateSceneRowsOfConsecutiveRowsMovesEverySh) {
  const GaussianStore before = MakeSyntheticStreet({.num_gaussians = 1'003, .seed = 7, .sh_degree = 3});
  GaussianStore after = before;
  std::vector<uint32_t> rows;
  for (uint32_t i = 0; i < 300; ++i) {
    if (i != 100) rows.push_back(i);  // tiles; after the gap, rows one by one up to a line start
  }
  for (uint32_t i = 301; i < before.size(); i += 3) rows.push_back(i);       // singles
  for (uint32_t i : rows) {
    for (int k = 0; k < 48; ++k) after.sh[i * 48 + k] += 0.01f * static_cast<float>((i + k) % 13) - 0.06f;
    after.means[i * 3] += 0.03f;
  }
  ParamsChange change = ChangeOf(rows, 16);
  change.means = true;
  auto engine = CreateCpuEngine({.num_threads = 2});
  EXPECT_EQ(RowUpdatedRgb(*engine, before, after, change), UploadedRgb(*engine, after));
  GaussianStore bad = after;
  bad.sh[37 * 48 + 40] = std::nanf("");  // inside a tile, in a band
  absl::Status st;
  RowUpdatedRgb(*engine, before, bad, change, &st);
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument);
}

// Rows need not be sorted. Sixteen rows whose first and last look like a run (i0 .. i0 + 15) but
// that leave out one row in between and list another must not be taken as a tile: the left-out
// row's SH in the view (stale in a served field's buffer) must not reach the engine.
TEST(CpuBackward, UpdateSceneRowsTakesNoRowOutsideTheChange) {
  const GaussianStore before = MakeSyntheticStreet({.num_gaussians = 1'003, .seed = 9, .sh_degree = 3});
  GaussianStore stale = before;  // every row of the view changed; only the listed ones may land
  for (size_t i = 0; i < before.size(); ++i) {
    for (int k = 0; k < 3; ++k) stale.sh[i * 48 + k] += 1.5f;
  }
  auto engine = CreateCpuEngine({.num_threads = 2});
  const std::vector<float> before_rgb = UploadedRgb(*engine, before);
  int checked = 0;
  for (uint32_t i0 = 0; i0 + 16 < 400 && checked < 3; i0 += 16) {
    for (uint32_t left_out = i0 + 1; left_out < i0 + 15; ++left_out) {
      GaussianStore only_it = before;
      std::copy_n(&stale.sh[left_out * 48], 48, &only_it.sh[left_out * 48]);
      if (UploadedRgb(*engine, only_it) == before_rgb) continue;  // not visible: cannot tell
      std::vector<uint32_t> rows;
      for (uint32_t i = i0; i < i0 + 16; ++i) rows.push_back(i == left_out ? 900 + i0 / 16 : i);
      GaussianStore expected = before;
      for (uint32_t i : rows) std::copy_n(&stale.sh[i * 48], 48, &expected.sh[i * 48]);
      EXPECT_EQ(RowUpdatedRgb(*engine, before, stale, ChangeOf(rows, 16)), UploadedRgb(*engine, expected))
          << "rows " << i0 << ".." << i0 + 15 << " without " << left_out;
      ++checked;
      break;
    }
  }
  EXPECT_EQ(checked, 3) << "too few visible rows to test";
}

}  // namespace
}  // namespace streetsim
