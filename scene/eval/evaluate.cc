#include "scene/eval/evaluate.h"

#include <algorithm>
#include <cmath>

#include "render/common/thread_pool.h"
#include "scene/train/dynamic_pixels.h"
#include "scene/train/losses.h"

namespace streetsim::train {

absl::StatusOr<EvalResult> Evaluate(Engine& engine, const GaussianStore& scene, const std::vector<View>& views,
                                    const Eigen::Vector3f& background) {
  absl::StatusOr<SceneForView> sv = MakeSceneForView(engine, scene, nullptr);
  if (!sv.ok()) return sv.status();
  return EvaluateViews(engine, *sv, views, background);
}

absl::StatusOr<EvalResult> EvaluateSceneDir(Engine& engine, const std::string& dir, const GaussianStore& canonical,
                                            const std::vector<View>& views, const Eigen::Vector3f& background,
                                            const EvalFrameSink& sink) {
  absl::StatusOr<std::shared_ptr<const field::DeformationField>> f = LoadSceneField(dir);
  if (!f.ok()) return f.status();
  absl::StatusOr<SceneForView> sv = MakeSceneForView(engine, canonical, *f);
  if (!sv.ok()) return sv.status();
  return EvaluateViews(engine, *sv, views, background, sink);
}

absl::StatusOr<EvalResult> EvaluateViews(Engine& engine, const SceneForView& scene_for_view,
                                         const std::vector<View>& views, const Eigen::Vector3f& background,
                                         const EvalFrameSink& sink) {
  ThreadPool pool(0);
  EvalResult result;
  RenderOptions ro;
  ro.background = background;
  RenderOutput out;
  double sum_psnr = 0, sum_ssim = 0, sum_med = 0, sum_within = 0;
  int depth_frames = 0;
  double sum_dyn = 0, sum_stat = 0;
  int dyn_frames = 0, stat_frames = 0;
  for (const View& v : views) {
    absl::StatusOr<const DeviceScene*> dev = scene_for_view(v);
    if (!dev.ok()) return dev.status();
    if (absl::Status s = engine.Render(**dev, v.camera, ro, &out); !s.ok()) return s;
    const std::vector<float> gt = v.RgbFloat();
    std::vector<float> clamped(out.rgb.size());
    for (size_t i = 0; i < clamped.size(); ++i) clamped[i] = std::min(std::max(out.rgb[i], 0.0f), 1.0f);
    if (v.luminance_only) LuminanceRgb(clamped.data(), clamped.size() / 3, clamped.data());  // as it trained
    if (sink) {
      if (absl::Status s = sink(v, clamped); !s.ok()) return s;
    }
    FrameMetrics m;
    m.name = v.name;
    m.frame = v.frame;
    m.psnr = Psnr(clamped.data(), gt.data(), gt.size());
    m.ssim = Ssim(pool, clamped.data(), gt.data(), v.camera.width, v.camera.height, 0, nullptr);
    if (v.dynamic_pixels.size() * 3 == gt.size()) {
      m.psnr_dynamic = MaskedPsnr(clamped.data(), gt.data(), v.dynamic_pixels, 1);
      m.psnr_static = MaskedPsnr(clamped.data(), gt.data(), v.dynamic_pixels, 0);
      if (m.psnr_dynamic >= 0) sum_dyn += m.psnr_dynamic, ++dyn_frames;
      if (m.psnr_static >= 0) sum_stat += m.psnr_static, ++stat_frames;
    }
    std::vector<double> err;
    size_t within = 0;
    for (const DepthSample& d : v.lidar) {
      const float a = out.alpha[d.pixel];
      if (!(a > 0.5f) || !(d.depth > 0.01f && d.depth < 80.0f)) continue;
      const double e = std::abs(out.depth[d.pixel] / a - d.depth);
      err.push_back(e);
      within += e <= 0.05 * d.depth;
    }
    m.depth_points = err.size();
    if (!err.empty()) {
      std::nth_element(err.begin(), err.begin() + err.size() / 2, err.end());
      m.depth_median_abs_m = err[err.size() / 2];
      m.depth_within_5pct = static_cast<double>(within) / err.size();
      sum_med += m.depth_median_abs_m;
      sum_within += m.depth_within_5pct;
      ++depth_frames;
    }
    sum_psnr += m.psnr;
    sum_ssim += m.ssim;
    result.frames.push_back(m);
  }
  const double n = std::max<size_t>(1, result.frames.size());
  result.mean.name = "mean";
  result.mean.psnr = sum_psnr / n;
  result.mean.ssim = sum_ssim / n;
  result.mean.depth_median_abs_m = depth_frames ? sum_med / depth_frames : -1;
  result.mean.depth_within_5pct = depth_frames ? sum_within / depth_frames : -1;
  result.mean.psnr_dynamic = dyn_frames ? sum_dyn / dyn_frames : -1;
  result.mean.psnr_static = stat_frames ? sum_stat / stat_frames : -1;
  return result;
}

}  // namespace streetsim::train
