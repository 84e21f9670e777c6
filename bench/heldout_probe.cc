// Where a trained scene's error on a log's views comes from (docs/field.md "What limits held-out
// PSNR"). Per view: its PSNR as `streetsim eval` renders it; the PSNR after a small search over the
// camera pose (are the log's poses the limit?); the PSNR with the field evaluated at the view's
// time plus offsets (is the field's time aligned with the images?); the squared error by sixths of
// the image width (where in the image is it?). With --region, how far the field carries the
// Gaussians that project into an image rectangle over the whole log (does a vehicle move, or is it
// recoloured in place?).
//   heldout_probe --scene DIR --log PATH [--split test|train] [--frames 3,7,11]
//                 [--resolution-scale 1] [--time-offsets-ms -50,50] [--no-pose-search]
//                 [--region x0,y0,x1,y1 --region-max-depth-m 15]   (pixels of the first frame's view)
// The pose search is coordinate descent over a rotation (camera axes) and a translation of the
// camera: steps 2 mrad and 4 cm, halved over five rounds, each step kept while the PSNR rises.
// It is a diagnostic upper bound on what pose noise costs a view, not an evaluation protocol.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <Eigen/Geometry>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/ply_io.h"
#include "scene/log/open_log.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/losses.h"
#include "scene/train/pose_refinement.h"
#include "scene/train/trainer.h"

using namespace streetsim;

namespace {

[[noreturn]] void Die(int code, const std::string& why) {
  std::fprintf(stderr, "heldout_probe: %s\n", why.c_str());
  std::exit(code);
}

template <typename T>
T OrDie(absl::StatusOr<T> v, int code = 1) {
  if (!v.ok()) Die(code, std::string(v.status().message()));
  return std::move(*v);
}

std::vector<double> ParseList(const std::string& s, const char* flag) {
  std::vector<double> out;
  for (absl::string_view part : absl::StrSplit(s, ',', absl::SkipEmpty())) {
    double v;
    if (!absl::SimpleAtod(part, &v) || !std::isfinite(v)) Die(2, std::string(flag) + ": not a number list");
    out.push_back(v);
  }
  return out;
}

class ViewScorer {
 public:
  ViewScorer(Engine& engine, const Eigen::Vector3f& background, const train::View& view)
      : engine_(engine), view_(view), gt_(view.RgbFloat()) {
    options_.background = background;
  }
  // PSNR of `scene` rendered from the view's camera moved by `delta` (in the camera's frame).
  double Psnr(const DeviceScene& scene, const Eigen::Isometry3d& delta) {
    PinholeCamera camera = view_.camera;
    camera.T_world_from_cam = view_.camera.T_world_from_cam * delta;
    if (absl::Status s = engine_.Render(scene, camera, options_, &out_); !s.ok()) Die(1, std::string(s.message()));
    clamped_.resize(out_.rgb.size());
    for (size_t i = 0; i < clamped_.size(); ++i) clamped_[i] = std::clamp(out_.rgb[i], 0.0f, 1.0f);
    return train::Psnr(clamped_.data(), gt_.data(), gt_.size());
  }
  // Mean squared error of the last render by sixths of the width.
  std::vector<double> StripMse() const {
    const int w = view_.camera.width, h = view_.camera.height;
    std::vector<double> sum(6, 0), count(6, 0);
    for (int y = 0; y < h; ++y) {
      for (int x = 0; x < w; ++x) {
        for (int c = 0; c < 3; ++c) {
          const size_t i = (static_cast<size_t>(y) * w + x) * 3 + c;
          const double r = clamped_[i] - gt_[i];
          sum[x * 6 / w] += r * r;
          count[x * 6 / w] += 1;
        }
      }
    }
    for (int k = 0; k < 6; ++k) sum[k] /= std::max(1.0, count[k]);
    return sum;
  }

 private:
  Engine& engine_;
  const train::View& view_;
  const std::vector<float> gt_;
  RenderOptions options_;
  RenderOutput out_;
  std::vector<float> clamped_;
};

// p = rotation about the camera's x, y, z (rad), then translation (m).
Eigen::Isometry3d Delta(const double p[6]) {
  Eigen::Isometry3d d = Eigen::Isometry3d::Identity();
  d.linear() = (Eigen::AngleAxisd(p[0], Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(p[1], Eigen::Vector3d::UnitY()) *
                Eigen::AngleAxisd(p[2], Eigen::Vector3d::UnitZ()))
                   .toRotationMatrix();
  d.translation() = Eigen::Vector3d(p[3], p[4], p[5]);
  return d;
}

double SearchPose(ViewScorer& scorer, const DeviceScene& scene, double start_psnr, double p[6]) {
  double best = start_psnr;
  for (int round = 0; round < 5; ++round) {
    for (int k = 0; k < 6; ++k) {
      const double step = (k < 3 ? 2e-3 : 0.04) / (1 << round);
      for (int sign : {+1, -1}) {
        for (;;) {
          double q[6];
          std::copy(p, p + 6, q);
          q[k] += sign * step;
          const double s = scorer.Psnr(scene, Delta(q));
          if (!(s > best + 1e-4)) break;
          best = s;
          std::copy(q, q + 6, p);
        }
      }
    }
  }
  return best;
}

double Quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * v.size()))];
}

// The Gaussians (opacity >= 0.3) whose deformed means project into `rect` at the view's time,
// nearer than max_depth_m; per Gaussian the diagonal of its position's box over the log (sampled
// every 100 ms) and its largest distance from the canonical position.
void ProbeRegion(const field::DeformationField& f, const GaussianStore& canonical, const train::View& view,
                 const std::vector<double>& rect, double max_depth_m, const field::FieldTimeRange& range) {
  ThreadPool pool(0);
  const GaussianStore at_view = OrDie(train::DeformedStore(f, canonical, view.time_us, pool));
  const Eigen::Isometry3d T_cam_from_world = view.camera.T_world_from_cam.inverse();
  std::vector<size_t> selected;
  for (size_t i = 0; i < at_view.size(); ++i) {
    if (1 / (1 + std::exp(-at_view.opacity_logits[i])) < 0.3) continue;
    const Eigen::Vector3d p_cam = T_cam_from_world * Eigen::Vector3f(&at_view.means[3 * i]).cast<double>();
    if (p_cam.z() < 0.5 || p_cam.z() > max_depth_m) continue;
    const double u = view.camera.fx * p_cam.x() / p_cam.z() + view.camera.cx;
    const double v = view.camera.fy * p_cam.y() / p_cam.z() + view.camera.cy;
    if (u >= rect[0] && u < rect[2] && v >= rect[1] && v < rect[3]) selected.push_back(i);
  }
  std::vector<Eigen::Vector3d> lo(selected.size(), Eigen::Vector3d::Constant(1e30));
  std::vector<Eigen::Vector3d> hi(selected.size(), Eigen::Vector3d::Constant(-1e30));
  std::vector<double> from_canonical(selected.size(), 0);
  for (int64_t t_us = range.start_us; t_us <= range.end_us; t_us += 100000) {
    const GaussianStore at_t = OrDie(train::DeformedStore(f, canonical, t_us, pool));
    for (size_t k = 0; k < selected.size(); ++k) {
      const Eigen::Vector3d p = Eigen::Vector3f(&at_t.means[3 * selected[k]]).cast<double>();
      const Eigen::Vector3d c = Eigen::Vector3f(&canonical.means[3 * selected[k]]).cast<double>();
      lo[k] = lo[k].cwiseMin(p);
      hi[k] = hi[k].cwiseMax(p);
      from_canonical[k] = std::max(from_canonical[k], (p - c).norm());
    }
  }
  std::vector<double> box;
  for (size_t k = 0; k < selected.size(); ++k) box.push_back((hi[k] - lo[k]).norm());
  std::printf("\nregion %g,%g,%g,%g of frame %d, nearer than %g m: %zu Gaussians\n", rect[0], rect[1], rect[2], rect[3],
              view.frame, max_depth_m, selected.size());
  std::printf("| | p10 | p50 | p90 | p99 | max |\n|---|---|---|---|---|---|\n");
  for (const auto& [name, v] : {std::pair<const char*, const std::vector<double>&>{"position box over the log (m)", box},
                                {"largest |Δx| from canonical (m)", from_canonical}}) {
    std::printf("| %s | %.2f | %.2f | %.2f | %.2f | %.2f |\n", name, Quantile(v, .1), Quantile(v, .5), Quantile(v, .9),
                Quantile(v, .99), Quantile(v, 1));
  }
}

}  // namespace

int main(int argc, char** argv) {
  std::string scene_dir, log_path, split = "test", frames_arg, offsets_arg, region_arg;
  double scale = 1.0, max_depth_m = 15;
  bool pose_search = true;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) Die(2, a + " needs a value");
      return argv[++i];
    };
    if (a == "--scene") scene_dir = next();
    else if (a == "--log") log_path = next();
    else if (a == "--split") split = next();
    else if (a == "--frames") frames_arg = next();
    else if (a == "--time-offsets-ms") offsets_arg = next();
    else if (a == "--region") region_arg = next();
    else if (a == "--no-pose-search") pose_search = false;
    else if (a == "--resolution-scale") {
      if (!absl::SimpleAtod(next(), &scale) || !(scale > 0 && scale <= 1)) Die(2, "--resolution-scale in (0, 1]");
    } else if (a == "--region-max-depth-m") {
      if (!absl::SimpleAtod(next(), &max_depth_m) || !(max_depth_m > 0)) Die(2, "--region-max-depth-m > 0");
    } else {
      Die(2, "unknown flag " + a);
    }
  }
  if (scene_dir.empty() || log_path.empty()) Die(2, "usage: heldout_probe --scene DIR --log PATH [flags]");
  if (split != "test" && split != "train") Die(2, "--split test|train");
  const std::vector<double> frames = ParseList(frames_arg, "--frames");
  const std::vector<double> offsets_ms = ParseList(offsets_arg, "--time-offsets-ms");
  const std::vector<double> rect = ParseList(region_arg, "--region");
  if (!region_arg.empty() && (rect.size() != 4 || frames.empty())) Die(2, "--region x0,y0,x1,y1 needs --frames");

  const DriveLog log = OrDie(OpenLog(log_path), 2);
  const train::SceneMeta meta = OrDie(train::ReadSceneMeta(scene_dir), 2);
  train::DatasetOptions dopt;
  dopt.resolution_scale = scale;
  dopt.holdout_every = meta.holdout_every;
  dopt.split = split == "test" ? train::Split::kTest : train::Split::kTrain;
  dopt.load_depth = false;
  std::vector<train::View> views = OrDie(train::LoadViews(log, dopt), 2);
  // A scene trained with --pose-refinement is probed at its corrected poses, as eval measures it.
  if (absl::StatusOr<std::vector<train::PoseCorrection>> c = train::ReadPoseCorrections(scene_dir); c.ok()) {
    train::ApplyPoseCorrections(*c, &views);
    std::printf("poses: the scene's corrections (%s)\n", train::kPoseCorrectionsFileName);
  } else if (!absl::IsNotFound(c.status())) {
    Die(2, std::string(c.status().message()));
  }
  const GaussianStore canonical = OrDie(ReadGaussianPly(scene_dir + "/scene.ply"), 2);
  const std::shared_ptr<const field::DeformationField> f = OrDie(train::LoadSceneField(scene_dir), 2);
  if (!rect.empty() && !f) Die(2, "--region needs a scene with a field");
  if (!offsets_ms.empty() && !f) Die(2, "--time-offsets-ms needs a scene with a field");
  std::unique_ptr<Engine> engine = OrDie(CreateEngine(Backend::kCpu));
  const train::SceneForView scene_for_view = OrDie(train::MakeSceneForView(*engine, canonical, f));
  auto wanted = [&](int frame) {
    return frames.empty() || std::find(frames.begin(), frames.end(), frame) != frames.end();
  };

  std::printf("scene %s, %s views, scale %g\n\n", scene_dir.c_str(), split.c_str(), scale);
  std::printf("| frame | PSNR | pose-searched | gain | rotation x y z (mdeg) | translation x y z (cm) | MSE x1e3 by "
              "sixth of width |\n|---|---|---|---|---|---|---|\n");
  double sum_base = 0, sum_searched = 0;
  int n = 0;
  std::vector<std::string> offset_rows;
  for (const train::View& v : views) {
    if (!wanted(v.frame)) continue;
    ViewScorer scorer(*engine, meta.background, v);
    const DeviceScene* scene = OrDie(scene_for_view(v));
    const double base = scorer.Psnr(*scene, Eigen::Isometry3d::Identity());
    const std::vector<double> strips = scorer.StripMse();
    double p[6] = {0, 0, 0, 0, 0, 0};
    const double searched = pose_search ? SearchPose(scorer, *scene, base, p) : base;
    const double mdeg = 180e3 / M_PI;
    std::printf("| %d | %.2f | %.2f | %+.2f | %.0f %.0f %.0f | %.1f %.1f %.1f |", v.frame, base, searched,
                searched - base, p[0] * mdeg, p[1] * mdeg, p[2] * mdeg, p[3] * 100, p[4] * 100, p[5] * 100);
    for (double s : strips) std::printf(" %.1f", s * 1e3);
    std::printf(" |\n");
    sum_base += base, sum_searched += searched, ++n;
    std::string row = "| " + std::to_string(v.frame) + " |";
    for (double ms : offsets_ms) {
      train::View shifted;
      shifted.time_us = v.time_us + static_cast<int64_t>(std::llround(ms * 1000));
      const DeviceScene* at = OrDie(scene_for_view(shifted));
      char cell[32];
      std::snprintf(cell, sizeof cell, " %.2f |", scorer.Psnr(*at, Eigen::Isometry3d::Identity()));
      row += cell;
    }
    offset_rows.push_back(row);
    std::fflush(stdout);
  }
  if (n == 0) Die(2, "no view of the split has one of --frames");
  std::printf("| mean (%d views) | %.2f | %.2f | %+.2f | | | |\n", n, sum_base / n, sum_searched / n,
              (sum_searched - sum_base) / n);
  if (!offsets_ms.empty()) {
    std::printf("\nPSNR with the field at the view's time plus (ms):\n\n| frame |");
    for (double ms : offsets_ms) std::printf(" %+g |", ms);
    std::printf("\n|---|");
    for (size_t k = 0; k < offsets_ms.size(); ++k) std::printf("---|");
    std::printf("\n");
    for (const std::string& r : offset_rows) std::printf("%s\n", r.c_str());
  }
  if (!rect.empty()) {
    for (const train::View& v : views) {
      if (v.frame != static_cast<int>(frames[0])) continue;
      ProbeRegion(*f, canonical, v, rect, max_depth_m, f->time_range());
    }
  }
  return 0;
}
