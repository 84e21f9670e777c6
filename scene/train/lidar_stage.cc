#include "scene/train/lidar_stage.h"

#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "render/lidar/lidar_sweep.h"
#include "scene/eval/lidar_eval.h"

namespace streetsim::train {
namespace {

inline float Sigmoid(float x) { return 1.0f / (1.0f + std::exp(-x)); }

}  // namespace

LidarLossTerms LidarFrameLoss(const float* range_sum, const float* alpha, const float* intensity_sum,
                              const LidarFrameTarget& target, const LidarLossWeights& w, float* d_range_sum,
                              float* d_alpha, float* d_intensity_sum) {
  const size_t rays = target.range.size();
  LidarLossTerms t;
  // A zero weight skips its term (and its gradient) entirely.
  if (w.range > 0) {
    t.range_l1_m = LidarRangeL1(range_sum, alpha, target.range.data(), rays, w.range, d_range_sum, d_alpha);
  }
  if (w.ret > 0) t.return_bce = LidarReturnBce(alpha, target.range.data(), rays, w.ret, d_alpha);
  if (w.intensity > 0) {
    t.intensity_l1 = LidarIntensityL1(intensity_sum, alpha, target.range.data(), target.intensity.data(), rays,
                                      w.intensity, d_intensity_sum, d_alpha);
  }
  t.total = w.range * t.range_l1_m + w.ret * t.return_bce + w.intensity * t.intensity_l1;
  return t;
}

std::vector<float> ReflectanceFromLogits(const std::vector<float>& logits) {
  std::vector<float> r(logits.size());
  for (size_t i = 0; i < logits.size(); ++i) r[i] = Sigmoid(logits[i]);
  return r;
}

absl::StatusOr<LidarLossTerms> LidarFrameLossAndGrads(LidarRenderer& renderer,
                                                      const std::vector<float>& reflectance_logit,
                                                      const LidarFrameTarget& target, const LidarLossWeights& weights,
                                                      const LidarGradOptions& options, LidarGaussianGrads* grads) {
  if (reflectance_logit.size() != renderer.uploaded_size()) {
    return absl::InvalidArgumentError(absl::StrCat(reflectance_logit.size(), " reflectance logits for ",
                                                   renderer.uploaded_size(), " uploaded Gaussians"));
  }
  const size_t rays = static_cast<size_t>(target.model.beams()) * target.model.columns;
  if (target.range.size() != rays || target.intensity.size() != rays) {
    return absl::InvalidArgumentError("LiDAR target does not match its model's range image");
  }
  const std::vector<float> refl = ReflectanceFromLogits(reflectance_logit);
  LidarRenderOptions ro;
  ro.reflectance = &refl;
  ro.kernel = options.kernel;
  ro.keep_for_backward = true;
  ro.sweep_start_us = target.sweep_start_us;
  LidarRenderOutput out;
  if (absl::Status s = renderer.Render(target.model, target.sweep, ro, &out); !s.ok()) return s;
  std::vector<float> d_range(rays, 0.0f), d_alpha(rays, 0.0f), d_int(rays, 0.0f);
  const LidarLossTerms terms = LidarFrameLoss(out.range_sum.data(), out.alpha.data(), out.intensity_sum.data(),
                                              target, weights, d_range.data(), d_alpha.data(), d_int.data());
  LidarUpstreamGrads up;
  up.d_range_sum = d_range.data();
  up.d_alpha = d_alpha.data();
  up.d_intensity_sum = d_int.data();
  if (absl::Status s = renderer.Backward(up, grads, options.deterministic); !s.ok()) return s;
  // The renderer's gradient is w.r.t. the reflectance in [0, 1]; the parameter is its logit.
  for (size_t i = 0; i < refl.size(); ++i) grads->reflectance[i] *= refl[i] * (1.0f - refl[i]);
  return terms;
}

LidarStage::LidarStage(const DriveLog& log, const LidarStageOptions& options)
    : log_(&log), options_(options), renderer_(options.num_threads) {}

absl::StatusOr<std::unique_ptr<LidarStage>> LidarStage::Create(const DriveLog& log,
                                                               const LidarStageOptions& options) {
  if (options.columns < 16 || options.columns > 8192) {
    return absl::InvalidArgumentError(absl::StrCat("LiDAR training columns must be in 16..8192, not ",
                                                   options.columns));
  }
  if (options.every < 1) return absl::InvalidArgumentError("the LiDAR step interval must be >= 1");
  const LidarLossWeights& w = options.weights;
  for (float x : {w.range, w.ret, w.intensity}) {
    if (!(x >= 0 && std::isfinite(x))) return absl::InvalidArgumentError("LiDAR loss weights must be finite and >= 0");
  }
  if (!(options.reflectance_lr > 0 && std::isfinite(options.reflectance_lr))) {
    return absl::InvalidArgumentError("the reflectance learning rate must be > 0");
  }
  if (log.frames.empty()) return absl::InvalidArgumentError("the log has no frames");
  return std::unique_ptr<LidarStage>(new LidarStage(log, options));
}

absl::StatusOr<const LidarFrameTarget*> LidarStage::Target(int frame) {
  if (frame < 0 || frame >= static_cast<int>(log_->frames.size())) {
    return absl::InvalidArgumentError(absl::StrCat("frame ", frame, " is not in the log"));
  }
  if (auto it = targets_.find(frame); it != targets_.end()) return it->second.get();
  const Frame& f = log_->frames[frame];
  if (f.lidars.empty()) {
    targets_[frame] = nullptr;
    return static_cast<const LidarFrameTarget*>(nullptr);
  }
  const LidarObservation& obs = f.lidars[0];
  if (obs.lidar < 0 || obs.lidar >= static_cast<int>(log_->lidars.size())) {
    return absl::InvalidArgumentError(absl::StrCat("frame ", frame, ": LiDAR index ", obs.lidar, " not in the rig"));
  }
  auto t = std::make_unique<LidarFrameTarget>();
  t->model = KittiHdl64e(options_.columns);
  t->model.T_ego_from_lidar = log_->lidars[obs.lidar].T_ego_from_lidar;
  // As EvaluateLidar: a rolling sweep centred on the scan's time stamp.
  t->sweep = LidarSweepPose::Static(f.T_world_from_ego * t->model.T_ego_from_lidar);
  t->sweep_start_us = obs.time_us;
  if (options_.rolling_sweep) {
    const int64_t half_us = t->model.sweep_duration_us / 2;
    t->sweep_start_us = obs.time_us - half_us;
    t->sweep.T_world_from_lidar_start = LogEgoPoseAt(*log_, t->sweep_start_us) * t->model.T_ego_from_lidar;
    t->sweep.T_world_from_lidar_end =
        LogEgoPoseAt(*log_, t->sweep_start_us + t->model.sweep_duration_us) * t->model.T_ego_from_lidar;
  }
  absl::StatusOr<LidarScan> scan = LoadLidarScan(obs.path);
  if (!scan.ok()) return scan.status();
  BinPointsToRangeImage(t->model, scan->points, &scan->reflectance, &t->range, &t->intensity);
  const LidarFrameTarget* raw = t.get();
  targets_[frame] = std::move(t);
  return raw;
}

absl::StatusOr<double> LidarStage::Step(TrainState* st, int frame, int64_t iteration, GaussianGrads* grads,
                                        const std::vector<float>* render_means) {
  if (iteration % options_.every != 0) return 0.0;
  absl::StatusOr<const LidarFrameTarget*> target = Target(frame);
  if (!target.ok()) return target.status();
  if (*target == nullptr) return 0.0;
  // Timed after the target: a scan's first use also reads and bins it (once per frame).
  const auto t0 = std::chrono::steady_clock::now();
  const size_t n = st->size();
  if (grads->means.size() != n * 3 || grads->opacity_logits.size() != n) {
    return absl::InvalidArgumentError("LiDAR step: the camera gradients do not match the state's Gaussians");
  }
  if (render_means != nullptr && render_means->size() != n * 3) {
    return absl::InvalidArgumentError("LiDAR step: the deformed means do not match the state's Gaussians");
  }
  if (st->reflectance_logit.size() != n) {
    if (!st->reflectance_logit.empty()) {
      return absl::FailedPreconditionError("LiDAR step: reflectance logits do not match the Gaussians");
    }
    st->reflectance_logit.assign(n, 0.0f);
    st->reflectance_m.assign(n, 0.0f);
    st->reflectance_v.assign(n, 0.0f);
    st->reflectance_step = 0;
  }
  // The renderer needs no colour: uploading a degree-0 copy spares Validate() the 48 SH
  // coefficients per Gaussian (it checks every float for finiteness).
  geometry_.sh_degree = 0;
  geometry_.means = render_means != nullptr ? *render_means : st->params.means;
  geometry_.log_scales = st->params.log_scales;
  geometry_.rotations = st->params.rotations;
  geometry_.opacity_logits = st->params.opacity_logits;
  geometry_.sh.assign(n * 3, 0.0f);
  geometry_.normals.clear();
  if (absl::Status s = renderer_.Upload(geometry_); !s.ok()) return s;
  LidarGradOptions go;
  go.deterministic = options_.deterministic;
  absl::StatusOr<LidarLossTerms> terms =
      LidarFrameLossAndGrads(renderer_, st->reflectance_logit, **target, options_.weights, go, &grads_);
  if (!terms.ok()) return terms.status();
  auto add = [](std::vector<float>& dst, const std::vector<float>& src) {
    for (size_t i = 0; i < dst.size(); ++i) dst[i] += src[i];
  };
  add(grads->means, grads_.means);
  add(grads->log_scales, grads_.log_scales);
  add(grads->rotations, grads_.rotations);
  add(grads->opacity_logits, grads_.opacity_logits);
  st->reflectance_step += 1;
  AdamStepSmall(st->reflectance_logit.data(), grads_.reflectance.data(), st->reflectance_m.data(),
                st->reflectance_v.data(), n, options_.reflectance_lr, st->reflectance_step);
  last_ = *terms;
  ++steps_;
  total_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return terms->total;
}

}  // namespace streetsim::train
