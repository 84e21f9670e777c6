#include "scene/train/train_loop.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <limits>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "absl/strings/cord.h"
#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/common/checked_file.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/ply_io.h"
#include "scene/train/checkpoint_run.h"
#include "scene/train/losses.h"
#include "scene/eval/metrics_json.h"
#include "scene/train/parts/gradient_guard_part.h"
#include "scene/train/parts/lidar_part.h"
#include "scene/train/parts/motion_prior_part.h"
#include "scene/train/parts/run_meter.h"
#include "scene/train/train_outputs.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;

double SceneExtent(const std::vector<View>& views) {
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const View& v : views) mean += v.camera.T_world_from_cam.translation();
  mean /= std::max<size_t>(1, views.size());
  double r = 0;
  for (const View& v : views) r = std::max(r, (v.camera.T_world_from_cam.translation() - mean).norm());
  return r > 1e-6 ? 1.1 * r : 1.0;
}

int NextView(TrainState* s, int num_views) {
  if (s->view_queue.empty()) {
    for (int i = 0; i < num_views; ++i) s->view_queue.push_back(i);
  }
  std::uniform_int_distribution<size_t> pick(0, s->view_queue.size() - 1);
  const size_t k = pick(s->rng);
  const int v = s->view_queue[k];
  s->view_queue.erase(s->view_queue.begin() + static_cast<std::ptrdiff_t>(k));
  return v;
}

// The field's time axis when the options give none: the views' time range.
field::FieldTimeRange ViewsTimeRange(const std::vector<View>& a, const std::vector<View>& b) {
  field::FieldTimeRange r{std::numeric_limits<int64_t>::max(), std::numeric_limits<int64_t>::min()};
  for (const std::vector<View>* vs : {&a, &b})
    for (const View& v : *vs) r.start_us = std::min(r.start_us, v.time_us), r.end_us = std::max(r.end_us, v.time_us);
  if (r.start_us > r.end_us) r = {0, 0};
  return r;
}

}  // namespace

TrainLoop::TrainLoop(const std::vector<View>& views, const std::vector<View>& heldout, const std::string& out_dir,
                     const TrainOptions& options, const std::function<void(const Progress&)>& progress)
    : views_(views),
      heldout_(heldout),
      out_dir_(out_dir),
      ckpt_path_((fs::path(out_dir) / "checkpoint.bin").string()),
      opt_(options),
      progress_(progress),
      appearance_(options.exposure, options.sky, options.hyper),
      densification_(options.hyper, options.iterations, options.write_outputs) {}

absl::Status TrainLoop::LoadOrInitState(const GaussianStore* init) {
  const int num_views = static_cast<int>(views_.size());
  if (opt_.resume && fs::exists(ckpt_path_)) {
    absl::StatusOr<TrainState> loaded = LoadCheckpoint(ckpt_path_);
    if (!loaded.ok()) return loaded.status();
    st_ = std::move(*loaded);
    if (opt_.exposure && st_.exposure.size() != static_cast<size_t>(num_views) * 12) {
      return absl::FailedPreconditionError("checkpoint was written for a different set of views");
    }
    LOG(INFO) << "resumed from " << ckpt_path_ << " at iteration " << st_.iteration;
    return absl::OkStatus();
  }
  if (init == nullptr) return absl::InvalidArgumentError("no initial scene");
  st_ = TrainState::Init(*init, SceneExtent(views_), num_views, opt_.seed);
  appearance_.InitSky(views_, &st_);
  LOG(INFO) << "initial scene: " << st_.size() << " Gaussians, extent " << st_.extent << " m, " << num_views
            << " training views";
  return absl::OkStatus();
}

absl::Status TrainLoop::AssembleParts() {
  absl::StatusOr<std::unique_ptr<PosePart>> poses =
      PosePart::Create(opt_.pose_refinement, static_cast<int>(views_.size()), opt_.hyper, &st_);
  if (!poses.ok()) return poses.status();
  poses_ = std::move(*poses);

  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(opt_.backend);
  if (!engine.ok()) return engine.status();
  engine_ = std::move(*engine);

  const bool dynamic = opt_.field.mode == FieldMode::kS3Gaussian;
  FieldPartOptions fo;
  fo.field = opt_.field;
  fo.field.seed += opt_.seed;
  fo.field.device = ResolveFieldDevice(opt_.field.device, opt_.backend);
  if (dynamic && fo.field.time_range.start_us == 0 && fo.field.time_range.end_us == 0) {
    fo.field.time_range = ViewsTimeRange(views_, heldout_);
  }
  fo.iterations = opt_.iterations;
  fo.deterministic = opt_.deterministic;
  absl::StatusOr<std::unique_ptr<FieldPart>> field = MakeFieldPart(fo, out_dir_, st_);
  if (!field.ok()) return field.status();
  field_ = std::move(*field);

  // A resumed run goes on with its checkpoint's record of the guard.
  if (opt_.resume && st_.iteration > 0) {
    std::optional<DivergenceGuardState> g = ReadCheckpointGuard(out_dir_, st_.iteration);
    if (g && g->image_width == views_[0].camera.width) guard_.Restore(*g);
  }

  parts_.push_back(poses_.get());
  if (opt_.lidar_weight > 0 && opt_.lidar_log != nullptr) {
    LidarStageOptions lo;
    lo.weights.range *= static_cast<float>(opt_.lidar_weight);
    lo.weights.ret *= static_cast<float>(opt_.lidar_weight);
    lo.weights.intensity *= static_cast<float>(opt_.lidar_weight);
    lo.every = opt_.lidar_every;
    lo.columns = opt_.lidar_columns;
    lo.deterministic = opt_.deterministic;
    absl::StatusOr<std::unique_ptr<LidarPart>> lidar = LidarPart::Create(*opt_.lidar_log, lo);
    if (!lidar.ok()) return lidar.status();
    owned_parts_.push_back(std::move(*lidar));
  }
  owned_parts_.push_back(std::make_unique<GradientGuardPart>());
  if (dynamic) {
    absl::StatusOr<std::unique_ptr<MotionPriorPart>> prior =
        MotionPriorPart::Create(opt_.motion_prior, opt_.lidar_log, opt_.holdout_every);
    if (!prior.ok()) return prior.status();
    owned_parts_.push_back(std::move(*prior));
  }
  for (const std::unique_ptr<IterationPart>& p : owned_parts_) parts_.push_back(p.get());
  return absl::OkStatus();
}

absl::Status TrainLoop::Setup(const GaussianStore* init) {
  if (opt_.iterations < 1) return absl::InvalidArgumentError("iterations must be >= 1");
  if (views_.empty()) return absl::InvalidArgumentError("no training views");
  std::error_code ec;
  fs::create_directories(out_dir_, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", out_dir_, ": ", ec.message()));
  if (absl::Status s = LoadOrInitState(init); !s.ok()) return s;
  if (absl::Status s = AssembleParts(); !s.ok()) return s;
  gt_cache_.resize(views_.size());
  return absl::OkStatus();
}

double TrainLoop::PhotometricLoss(const View& view, const std::vector<float>& gt, const std::vector<float>& image,
                                  double* psnr) {
  const Hyper& h = opt_.hyper;
  const int W = view.camera.width, H = view.camera.height;
  const size_t pixels = static_cast<size_t>(W) * H;
  d_rgb_.assign(pixels * 3, 0.0f);
  d_depth_.assign(pixels, 0.0f);
  // A grayscale camera beside colour ones supervises the render's luminance only (losses.h).
  const std::vector<float>* compared = &image;
  float* d_compared = d_rgb_.data();
  if (view.luminance_only) {
    luma_.resize(pixels * 3);
    LuminanceRgb(image.data(), pixels, luma_.data());
    d_luma_.assign(pixels * 3, 0.0f);
    compared = &luma_;
    d_compared = d_luma_.data();
  }
  const double l1 = L1Loss(pool_, compared->data(), gt.data(), pixels * 3, 1.0f, d_compared);
  const double ssim = Ssim(pool_, compared->data(), gt.data(), W, H, static_cast<float>(-h.lambda_dssim), d_compared);
  if (view.luminance_only) LuminanceBackward(d_luma_.data(), pixels, d_rgb_.data());
  double ld = 0;
  if (opt_.depth_loss) {
    ld = DepthLoss(out_.depth.data(), view.lidar, static_cast<float>(h.lambda_depth), d_depth_.data());
  }
  *psnr = Psnr(compared->data(), gt.data(), pixels * 3);
  return l1 + h.lambda_dssim * (1 - ssim) + h.lambda_depth * ld;
}

absl::StatusOr<double> TrainLoop::Iterate(int64_t it, double* psnr) {
  const Hyper& h = opt_.hyper;
  Iteration i;
  i.it = it;
  i.active_degree = std::min<int>(3, static_cast<int>(it / h.sh_degree_interval));
  i.view_index = NextView(&st_, static_cast<int>(views_.size()));
  const View& view = views_[i.view_index];
  i.view = &view;
  if (gt_cache_[i.view_index].empty()) gt_cache_[i.view_index] = view.RgbFloat();
  i.fine = field_->Fine(it);
  i.stage_it = field_->StageIteration(it);

  bool began = false;
  absl::StatusOr<GaussianParamsView> params = field_->Params(&st_, i.active_degree, view, it, pool_, &began);
  if (!params.ok()) return params.status();
  if (began) {
    guard_.Rebaseline(it);
    for (IterationPart* p : parts_) p->RowsChanged();
  }
  i.rendered = &*params;
  if (absl::Status s = engine_->UpdateSceneParams(*params, &scene_); !s.ok()) return s;
  RenderOptions ro;
  ro.background = appearance_.Background(st_);
  ro.keep_for_backward = true;
  const PinholeCamera camera = poses_->Camera(view, i.view_index, st_);
  i.camera = &camera;
  if (absl::Status s = engine_->Render(*scene_, camera, ro, &out_); !s.ok()) return s;

  const std::vector<float>& image = appearance_.Apply(st_, i.view_index, out_);
  double loss = PhotometricLoss(view, gt_cache_[i.view_index], image, psnr);
  const std::vector<float>& d_render = appearance_.Backward(&st_, i.view_index, out_, d_rgb_);
  BackwardOptions bo;
  bo.deterministic = opt_.deterministic;
  RenderOutputGrads og;
  og.rgb = d_render.data();
  og.depth = opt_.depth_loss ? d_depth_.data() : nullptr;
  if (absl::Status s = engine_->RenderBackward(*scene_, og, bo, &grads_); !s.ok()) return s;

  i.deformed_means = i.fine ? field_->DeformedMeans() : nullptr;
  for (IterationPart* p : parts_) {
    absl::StatusOr<double> l = p->AddGradients(i, &st_, &grads_, pool_);
    if (!l.ok()) return l.status();
    loss += *l;
  }
  absl::StatusOr<double> field_loss = field_->Backward(st_, i.active_degree, i.stage_it, &grads_, pool_);
  if (!field_loss.ok()) return field_loss.status();
  loss += *field_loss;
  for (IterationPart* p : parts_) p->AfterFieldBackward(i, &grads_);

  const DensifyEvents ev =
      densification_.Step(it, i.stage_it, grads_, view.camera.width, view.camera.height, &st_);
  if (ev.rows_changed) {
    if (absl::Status s = field_->RowsChanged(&st_, pool_); !s.ok()) return s;
    for (IterationPart* p : parts_) p->RowsChanged();
  }
  if (ev.opacity_reset) guard_.Rebaseline(it);
  // On iterations that replace the Gaussian tensors, 3DGS's Adam sees no gradient for them.
  if (!ev.replaced()) AdamStepGaussians(&st_, grads_, i.active_degree, i.stage_it, h, pool_);
  st_.iteration = it;
  return loss;
}

absl::Status TrainLoop::SaveCheckpoint() {
  saved_iteration_ = st_.iteration;
  if (absl::Status s = field_->SaveCheckpoint(out_dir_, st_.iteration); !s.ok()) return s;
  if (absl::Status s = train::SaveCheckpoint(st_, ckpt_path_); !s.ok()) return s;
  field_->RemoveOlderCheckpoints(out_dir_, st_.iteration);
  // The checkpoint's own state (checkpoint_run.h); the run's settings are config.json's.
  CheckpointRun run;
  run.iteration = st_.iteration;
  field_->Record(&run);
  run.guard = guard_.state(views_[0].camera.width);
  return WriteCheckpointRun(out_dir_, run);
}

void TrainLoop::LogSummaries(bool run_end) const {
  std::vector<std::string> lines = {field_->Summary()};
  if (run_end) {
    for (const IterationPart* p : parts_) lines.push_back(p->Summary());
  }
  for (const std::string& line : lines) {
    if (!line.empty()) {
      LOG(INFO) << line;
    }
  }
}

absl::StatusOr<TrainResult> TrainLoop::Run() {
  const int64_t first = st_.iteration + 1;
  RunMeter meter(first, opt_.iterations, field_->FirstStageEnd(), t_start_);
  bool said_suspicious = false;
  for (int64_t it = first; it <= opt_.iterations; ++it) {
    double psnr = 0;
    absl::StatusOr<double> loss = Iterate(it, &psnr);
    if (!loss.ok()) return loss.status();
    meter.Observe(it, *loss, psnr, st_.size(), &st_, &result_, progress_);
    const DivergenceGuard::Verdict verdict =
        opt_.divergence_guard ? guard_.Observe(it, *loss, psnr) : DivergenceGuard::Verdict::kFine;
    if (verdict == DivergenceGuard::Verdict::kDiverged) {
      // No checkpoint of the diverged state: the last one on disk is from before it.
      LogSummaries(false);
      absl::Status diverged = absl::AbortedError(
          absl::StrCat("diverged at iteration ", it, field_->Fine(it) ? " (fine stage)" : " (static stage)", ": ",
                       guard_.why(), "; the last checkpoint (iteration ",
                       std::max<int64_t>(saved_iteration_, first - 1), ") is from before"));
      diverged.SetPayload(kDivergedAtPayload, absl::Cord(absl::StrCat(it)));
      return diverged;
    }
    if (verdict == DivergenceGuard::Verdict::kSuspicious && !said_suspicious) {
      LOG(WARNING) << "iteration " << it << ": " << guard_.why() << ": no checkpoint until it recovers";
    }
    said_suspicious = verdict == DivergenceGuard::Verdict::kSuspicious;
    if (opt_.checkpoint_every > 0 && it % opt_.checkpoint_every == 0 && verdict == DivergenceGuard::Verdict::kFine) {
      if (absl::Status s = SaveCheckpoint(); !s.ok()) return s;
    }
    if (opt_.stop_requested != nullptr && opt_.stop_requested->load(std::memory_order_relaxed)) {
      if (saved_iteration_ != st_.iteration) {
        if (absl::Status s = SaveCheckpoint(); !s.ok()) return s;
      }
      LogSummaries(false);
      return absl::CancelledError(absl::StrCat("stopped at iteration ", it, " of ", opt_.iterations,
                                               ", checkpoint written: --resume continues from it"));
    }
    if (opt_.stop_after > 0 && it >= opt_.stop_after) {
      result_.iterations = it;
      result_.gaussians = st_.size();
      result_.seconds = std::chrono::duration<double>(Clock::now() - t_start_).count();
      return result_;
    }
  }
  if (absl::Status s = SaveCheckpoint(); !s.ok()) return s;
  result_.iterations = st_.iteration;
  result_.gaussians = st_.size();
  LogSummaries(true);
  if (opt_.write_outputs) {
    if (absl::Status s = WriteOutputs(); !s.ok()) return s;
  }
  result_.seconds = std::chrono::duration<double>(Clock::now() - t_start_).count();
  return result_;
}

absl::Status TrainLoop::WriteOutputs() {
  // The learned LiDAR reflectance as an extra vertex property (lidar_eval.h reads it).
  const std::vector<float> reflectance = ReflectanceFromLogits(st_.reflectance_logit);
  if (absl::Status s = WriteGaussianPly(st_.params, (fs::path(out_dir_) / "scene.ply").string(),
                                        st_.reflectance_logit.empty() ? nullptr : &reflectance);
      !s.ok()) {
    return s;
  }
  const Hyper& h = opt_.hyper;
  nlohmann::json meta;
  const Eigen::Vector3f bg = appearance_.Background(st_);
  meta["background"] = {bg[0], bg[1], bg[2]};
  meta["resolution_scale"] = opt_.resolution_scale;
  if (opt_.low_res) {  // provenance: the run's first iterations were at this scale
    meta["low_res_scale"] = opt_.low_res->resolution_scale;
    meta["low_res_iterations"] = opt_.low_res->iterations;
  }
  meta["holdout_every"] = opt_.holdout_every;
  meta["iterations"] = st_.iteration;
  meta["gaussians"] = st_.size();
  meta["extent_m"] = st_.extent;
  meta["seed"] = opt_.seed;
  meta["sky"] = opt_.sky;
  meta["exposure"] = opt_.exposure;
  meta["position_lr_decay_iterations"] = h.lr_decay_steps;  // the means' rate decay, per stage
  meta["densify_until"] = h.densify_until;                  // densification's end, per stage
  if (absl::Status s = field_->WriteOutputs(out_dir_, &meta); !s.ok()) return s;
  for (const IterationPart* p : parts_) p->Meta(&meta);
  if (absl::Status s = checked_file::WriteAtomically((fs::path(out_dir_) / "train_meta.json").string(),
                                                    meta.dump(2) + "\n");
      !s.ok()) {
    return s;
  }
  cv::Mat plot = PlotCurve(st_.curve);
  if (absl::Status s = WriteRgbPng((fs::path(out_dir_) / "curve.png").string(), plot); !s.ok()) return s;
  // The learned corrections of the training views; held-out views take them interpolated.
  absl::StatusOr<std::optional<std::vector<View>>> corrected = poses_->Finish(out_dir_, views_, st_, heldout_);
  if (!corrected.ok()) return corrected.status();
  if (heldout_.empty()) {
    std::error_code ec;
    fs::remove(fs::path(out_dir_) / kHeldoutMetricsFileName, ec);  // not this run's
    return absl::OkStatus();
  }
  return EvaluateHeldOut(*corrected ? **corrected : heldout_);
}

// Held-out metrics (each view at its own time when there is a field) and previews (render |
// ground truth).
absl::Status TrainLoop::EvaluateHeldOut(const std::vector<View>& test) {
  const Eigen::Vector3f bg = appearance_.Background(st_);
  absl::StatusOr<SceneForView> scene_for_view = MakeSceneForView(*engine_, st_.params, field_->SceneField());
  if (!scene_for_view.ok()) return scene_for_view.status();
  absl::StatusOr<EvalResult> ev = EvaluateViews(*engine_, *scene_for_view, test, bg);
  if (!ev.ok()) return ev.status();
  result_.heldout = *ev;
  // Machine-readable beside the scene (the server's job record reads it; metrics_json.h).
  if (absl::Status s = WriteHeldoutMetrics(out_dir_, result_.heldout); !s.ok()) return s;
  const fs::path pdir = fs::path(out_dir_) / "preview";
  std::error_code ec;
  fs::create_directories(pdir, ec);
  RenderOptions ro;
  ro.background = bg;
  const size_t step = std::max<size_t>(1, test.size() / 6);
  for (size_t i = 0; i < test.size(); i += step) {
    const View& v = test[i];
    absl::StatusOr<const DeviceScene*> dev = (*scene_for_view)(v);
    if (!dev.ok()) return dev.status();
    if (absl::Status s = engine_->Render(**dev, v.camera, ro, &out_); !s.ok()) return s;
    cv::Mat both;
    cv::hconcat(ToRgb8(out_.rgb, v.camera.width, v.camera.height), v.rgb8, both);
    char name[64];
    std::snprintf(name, sizeof(name), "heldout_frame%04d_cam%d.png", v.frame, v.camera_obs);
    if (absl::Status s = WriteRgbPng((pdir / name).string(), both); !s.ok()) return s;
  }
  return absl::OkStatus();
}

}  // namespace streetsim::train
