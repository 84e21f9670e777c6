// Held-out evaluation (docs/training.md "Evaluation"): PSNR, SSIM, LiDAR depth error and PSNR* of
// rendered views, for a static scene or a field scene deformed at each view's time. A training run
// ends with it (train_loop.h), `streetsim eval` runs it on a trained scene directory. Library
// streetsim_eval, between streetsim_train_core (views, metrics, a scene at a view's time: what it
// measures with) and streetsim_train (the loop, which ends with it); it keeps the train namespace
// its callers use.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"

namespace streetsim::train {

struct FrameMetrics {
  std::string name;
  int frame = 0;
  double psnr = 0, ssim = 0;
  double depth_median_abs_m = -1, depth_within_5pct = -1;  // -1: no LiDAR
  size_t depth_points = 0;
  // PSNR* (dynamic_pixels.h): on the view's dynamic pixels / the others; -1: no mask or no pixel.
  double psnr_dynamic = -1, psnr_static = -1;
};
struct EvalResult {
  std::vector<FrameMetrics> frames;
  FrameMetrics mean;
};

// Called once per evaluated view after its render (eval outputs, eval_outputs.h: decomposition
// images, video); `rgb` is the measured render, clamped to [0, 1] [H*W*3]. An error stops the eval.
using EvalFrameSink = std::function<absl::Status(const View& view, const std::vector<float>& rgb)>;

// Renders every view of `views` and measures it. background: the learned sky colour. The means
// of psnr_dynamic / psnr_static are over the views that have such pixels.
absl::StatusOr<EvalResult> Evaluate(Engine& engine, const GaussianStore& scene, const std::vector<View>& views,
                                    const Eigen::Vector3f& background);
// The same with a scene per view (a field scene deformed at each view's time).
absl::StatusOr<EvalResult> EvaluateViews(Engine& engine, const SceneForView& scene, const std::vector<View>& views,
                                         const Eigen::Vector3f& background, const EvalFrameSink& sink = nullptr);
// A trained scene directory's Gaussians (`canonical`, its scene.ply) with DIR/field.bin if any.
absl::StatusOr<EvalResult> EvaluateSceneDir(Engine& engine, const std::string& dir, const GaussianStore& canonical,
                                            const std::vector<View>& views, const Eigen::Vector3f& background,
                                            const EvalFrameSink& sink = nullptr);

}  // namespace streetsim::train
