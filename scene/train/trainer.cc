#include "scene/train/trainer.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "absl/strings/cord.h"
#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "render/common/thread_pool.h"
#include "scene/common/checked_file.h"
#include "scene/gaussians/ply_io.h"
#include "scene/init/initial_scene.h"
#include "scene/field/field_io.h"
#include "scene/train/divergence_guard.h"
#include "scene/train/dynamic_pixels.h"
#include "scene/train/gradient_guard.h"
#include "scene/train/losses.h"
#include "scene/train/metrics_json.h"
#include "scene/train/pose_refinement.h"
#include "scene/train/resolution_schedule.h"
#include "scene/train/train_outputs.h"

namespace streetsim::train {
namespace {

using Clock = std::chrono::steady_clock;
// More Gaussians than this with a non-finite gradient in one step is divergence, not one degenerate
// splat (gradient_guard.h).
constexpr double kMaxNonFiniteGradientFraction = 0.01;
double SecondsSince(Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); }

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

absl::Status CheckFieldOptions(const TrainOptions& opt) {
  if (opt.field.mode != FieldMode::kS3Gaussian) return absl::OkStatus();
  if (opt.field.static_iterations < 0 || opt.field.static_iterations >= opt.iterations) {
    return absl::InvalidArgumentError(absl::StrCat("--static-iterations must be in 0..", opt.iterations - 1,
                                                   " (below --iterations, the total), not ",
                                                   opt.field.static_iterations));
  }
  return opt.field.config.Validate();
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

absl::StatusOr<SceneMeta> ReadSceneMeta(const std::string& dir) {
  SceneMeta meta;
  const std::string path = (std::filesystem::path(dir) / "train_meta.json").string();
  std::ifstream f(path);
  if (!f) return meta;  // a scene.ply from elsewhere: black background, scale 1
  try {
    const nlohmann::json j = nlohmann::json::parse(f);
    for (int c = 0; c < 3; ++c) meta.background[c] = j.at("background").at(c).get<float>();
    meta.resolution_scale = j.at("resolution_scale").get<double>();
    meta.holdout_every = j.at("holdout_every").get<int>();
    meta.field = j.value("field", std::string("static"));
    meta.iterations = j.value("iterations", int64_t{0});
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
  return meta;
}

namespace {

// A copy of `log` with only frames [first_frame, end_frame) that are not held out: what scene init
// and the motion prior may see.
DriveLog TrainingFramesLog(const DriveLog& log, int first_frame, int end_frame, int holdout_every) {
  DriveLog train_log = log;
  train_log.frames.clear();
  for (int f = first_frame; f < end_frame; ++f)
    if (!IsHeldOut(f, holdout_every)) train_log.frames.push_back(log.frames[f]);
  return train_log;
}

}  // namespace

absl::StatusOr<GaussianStore> BuildTrainingInitialScene(const DriveLog& log, int first_frame, int end_frame,
                                                        const TrainOptions& opt) {
  const DriveLog train_log = TrainingFramesLog(log, first_frame, end_frame, opt.holdout_every);
  InitOptions iopt;
  iopt.voxel_m = opt.init_voxel_m;
  iopt.seed = static_cast<unsigned>(opt.seed + 1);
  InitStats istats;
  absl::StatusOr<GaussianStore> built = BuildInitialScene(train_log, iopt, &istats);
  if (!built.ok()) return built.status();
  LOG(INFO) << "initial scene: " << built->size() << " Gaussians (" << istats.source << ")";
  return built;
}

namespace {

// Train at one resolution (opt.resolution_scale); Train runs it once per resolution stage.
absl::StatusOr<TrainResult> TrainLogAtScale(const DriveLog& log, const std::string& out_dir, const TrainOptions& opt,
                                            const std::function<void(const Progress&)>& progress) {
  if (opt.iterations < 1) return absl::InvalidArgumentError("iterations must be >= 1");
  if (absl::Status s = CheckFieldOptions(opt); !s.ok()) return s;
  DatasetOptions dopt;
  dopt.grayscale = opt.grayscale_cameras;
  dopt.resolution_scale = opt.resolution_scale;
  dopt.holdout_every = opt.holdout_every;
  dopt.split = Split::kTrain;
  dopt.load_depth = opt.depth_loss;
  absl::StatusOr<std::vector<View>> views = LoadViews(log, dopt);
  if (!views.ok()) return views.status();
  if (views->empty()) return absl::InvalidArgumentError("the log has no training views");
  std::vector<View> test;
  if (opt.write_outputs && opt.holdout_every > 0) {
    dopt.split = Split::kTest;
    dopt.load_depth = true;
    absl::StatusOr<std::vector<View>> t = LoadViews(log, dopt);
    if (!t.ok()) return t.status();
    test = std::move(*t);
    // PSNR* of the held-out views (the masks read scans only, never trained on).
    if (absl::Status s = AttachDynamicPixels(log, &test); !s.ok()) return s;
  }
  TrainOptions topt = opt;
  if (topt.field.mode == FieldMode::kS3Gaussian && topt.field.time_range.start_us == 0 &&
      topt.field.time_range.end_us == 0 && !log.frames.empty()) {
    // The field's time axis spans the whole log, held-out frames included.
    topt.field.time_range = {log.frames.front().time_us, log.frames.back().time_us};
  }
  const std::string ckpt_path = (std::filesystem::path(out_dir) / "checkpoint.bin").string();
  std::optional<GaussianStore> init;
  if (!(opt.resume && std::filesystem::exists(ckpt_path))) {
    // The initial scene sees the training frames only: held-out frames are never used.
    absl::StatusOr<GaussianStore> built =
        BuildTrainingInitialScene(log, 0, static_cast<int>(log.frames.size()), opt);
    if (!built.ok()) return built.status();
    init = std::move(*built);
  }
  if (topt.lidar_log == nullptr) topt.lidar_log = &log;
  return TrainOnViews(*views, init ? &*init : nullptr, test, out_dir, topt, progress);
}

}  // namespace

absl::StatusOr<TrainResult> Train(const DriveLog& log, const std::string& out_dir, const TrainOptions& opt,
                                  const std::function<void(const Progress&)>& progress) {
  return TrainInResolutionStages(
      opt, out_dir, progress,
      [&](const TrainOptions& stage, const std::function<void(const Progress&)>& stage_progress) {
        return TrainLogAtScale(log, out_dir, stage, stage_progress);
      });
}

absl::StatusOr<TrainResult> TrainOnViews(const std::vector<View>& train_views, const GaussianStore* init,
                                         const std::vector<View>& heldout, const std::string& out_dir,
                                         const TrainOptions& opt,
                                         const std::function<void(const Progress&)>& progress) {
  const auto t_start = Clock::now();
  if (opt.iterations < 1) return absl::InvalidArgumentError("iterations must be >= 1");
  if (train_views.empty()) return absl::InvalidArgumentError("no training views");
  if (absl::Status s = CheckFieldOptions(opt); !s.ok()) return s;
  std::error_code ec;
  std::filesystem::create_directories(out_dir, ec);
  if (ec) return absl::InternalError(absl::StrCat("cannot create ", out_dir, ": ", ec.message()));
  const std::string ckpt_path = (std::filesystem::path(out_dir) / "checkpoint.bin").string();
  const std::vector<View>* views = &train_views;
  const int num_views = static_cast<int>(views->size());

  TrainState st;
  if (opt.resume && std::filesystem::exists(ckpt_path)) {
    absl::StatusOr<TrainState> loaded = LoadCheckpoint(ckpt_path);
    if (!loaded.ok()) return loaded.status();
    st = std::move(*loaded);
    if (opt.exposure && st.exposure.size() != static_cast<size_t>(num_views) * 12) {
      return absl::FailedPreconditionError("checkpoint was written for a different set of views");
    }
    LOG(INFO) << "resumed from " << ckpt_path << " at iteration " << st.iteration;
  } else {
    if (init == nullptr) return absl::InvalidArgumentError("no initial scene");
    st = TrainState::Init(*init, SceneExtent(*views), num_views, opt.seed);
    if (opt.sky) {
      // Start the environment colour at the mean of the training images' top rows.
      double acc[3] = {0, 0, 0};
      size_t cnt = 0;
      for (const View& v : *views) {
        for (int y = 0; y < std::max(1, v.rgb8.rows / 10); ++y)
          for (int x = 0; x < v.rgb8.cols; ++x, ++cnt)
            for (int c = 0; c < 3; ++c) acc[c] += v.rgb8.at<cv::Vec3b>(y, x)[c] / 255.0;
      }
      for (int c = 0; c < 3; ++c) st.sky[c] = static_cast<float>(acc[c] / std::max<size_t>(cnt, 1));
    }
    LOG(INFO) << "initial scene: " << st.size() << " Gaussians, extent " << st.extent << " m, " << num_views
              << " training views";
  }
  // A checkpoint that refines its poses goes on refining them: its scene sits in the corrected
  // trajectory's frame, and the log's poses would misplace every view of it.
  const bool refine_poses = opt.pose_refinement || !st.pose_delta.empty();
  if (refine_poses) {
    if (!opt.pose_refinement) LOG(INFO) << "the checkpoint refines its camera poses: so does this run";
    if (absl::Status s = PreparePoseCorrections(num_views, &st); !s.ok()) return s;
  }

  absl::StatusOr<std::unique_ptr<Engine>> engine = CreateEngine(opt.backend);
  if (!engine.ok()) return engine.status();
  ThreadPool pool(0);
  std::unique_ptr<DeviceScene> scene;
  RenderOutput out;
  GaussianGrads grads;
  std::vector<float> d_rgb, d_depth, d_pre, rgb_exp, luma, d_luma;
  std::vector<std::vector<float>> gt_cache(num_views);
  const Hyper& h = opt.hyper;
  TrainResult result;
  double psnr_window = 0;
  std::vector<double> recent_psnr;
  double recent_loss = 0;
  const int64_t first = st.iteration + 1;
  const auto t_loop = Clock::now();
  std::deque<std::pair<int64_t, double>> rate_window;  // (iteration, seconds) at progress reports

  // S3Gaussian's stages: static for static_its iterations, then the field (dynamic_stage.h).
  const bool dynamic = opt.field.mode == FieldMode::kS3Gaussian;
  const int64_t static_its = dynamic ? opt.field.static_iterations : opt.iterations;
  FieldOptions fopt = opt.field;
  fopt.seed += opt.seed;
  fopt.device = ResolveFieldDevice(opt.field.device, opt.backend);
  if (dynamic && fopt.time_range.start_us == 0 && fopt.time_range.end_us == 0) {
    fopt.time_range = ViewsTimeRange(train_views, heldout);
  }
  std::unique_ptr<DynamicStage> stage;
  auto log_fine_timings = [&] {
    if (stage && stage->timings().iterations > 0) {
      LOG(INFO) << stage->timings().Summary();
    }
  };
  // The field's backward sums MLP gradients per thread in scheduling order: one thread when the
  // run should be reproducible (docs/training.md "Reproducibility").
  std::unique_ptr<ThreadPool> serial_pool;
  ThreadPool* field_pool = &pool;
  if (dynamic && opt.deterministic) {
    serial_pool = std::make_unique<ThreadPool>(1);
    field_pool = serial_pool.get();
  }
  if (!dynamic && st.iteration > 0 && std::filesystem::exists(FieldCheckpointPath(out_dir, st.iteration))) {
    return absl::FailedPreconditionError("the checkpoint is from a --field s3gaussian run; resume it with that");
  }
  if (dynamic && st.iteration > static_its) {
    absl::StatusOr<std::unique_ptr<DynamicStage>> r =
        DynamicStage::Resume(FieldCheckpointPath(out_dir, st.iteration), fopt, st.iteration - static_its);
    if (!r.ok()) return r.status();
    stage = std::move(*r);
  }
  // The loss watched for divergence (divergence_guard.h); the fine stage's start and opacity
  // resets move it on purpose. A resumed run goes on with its checkpoint's record of it.
  DivergenceGuard guard;
  if (opt.resume && st.iteration > 0) {
    std::optional<DivergenceGuardState> g = ReadCheckpointGuard(out_dir, st.iteration);
    if (g && g->image_width == (*views)[0].camera.width) guard.Restore(*g);
  }
  // The field's checkpoint first (one file per iteration), then the Gaussians', then older fields.
  int64_t saved_iteration = -1;  // the last checkpoint's, so that a stop right after one is free
  auto save_checkpoint = [&]() -> absl::Status {
    saved_iteration = st.iteration;
    if (stage) {
      if (absl::Status s = stage->SaveCheckpoint(FieldCheckpointPath(out_dir, st.iteration)); !s.ok()) return s;
    }
    if (absl::Status s = SaveCheckpoint(st, ckpt_path); !s.ok()) return s;
    RemoveFieldCheckpoints(out_dir, stage ? st.iteration : -1);
    // Which field wrote these checkpoints, for a resume that does not say (checkpoint_run.h).
    CheckpointRun run;
    run.iteration = st.iteration;
    run.field = !dynamic ? "static" : opt.field.extended ? "extended" : "s3gaussian";
    if (dynamic) {
      run.static_iterations = static_its;
      run.field_lr = FieldLrSchedule{opt.field.hyper.lr_scale, opt.field.hyper.lr_decay_steps};
      run.field_motion_prior = opt.motion_prior.weight;
      run.field_motion_prior_all_scans = opt.motion_prior.all_scans;
    }
    run.low_res = opt.low_res;
    run.position_lr_decay_iterations = h.lr_decay_steps;
    run.densify_until = h.densify_until;
    run.guard = guard.state((*views)[0].camera.width);
    if (stage && stage->extended()) {
      run.field_extension_from = stage->extension_from_fine_iteration();
      run.field_ext_lr = FieldLrSchedule{opt.field.ext_hyper.lr_scale, opt.field.ext_hyper.lr_decay_steps};
    }
    if (refine_poses) {
      run.pose_refinement =
          PoseRefinementSchedule{h.pose_rotation_lr, h.pose_translation_lr, h.pose_refine_from, h.pose_refine_until};
    }
    return WriteCheckpointRun(out_dir, run);
  };

  // The fine stage's motion prior (built when the fine stage starts): the log's moving objects
  // tracked once, Gaussians assigned to them whenever the rows change.
  std::unique_ptr<MotionPrior> motion_prior;
  bool motion_prior_skipped = false;  // a preset's prior the log cannot carry
  bool prior_rows_changed = true;
  std::vector<float> prior_grad;
  if (dynamic && opt.motion_prior.weight > 0 && opt.lidar_log == nullptr) {
    return absl::FailedPreconditionError("the motion prior needs the log's LiDAR");
  }

  // LiDAR losses (lidar_stage.h) on every stage.
  std::unique_ptr<LidarStage> lidar_stage;
  if (opt.lidar_weight > 0 && opt.lidar_log != nullptr) {
    LidarStageOptions lo;
    lo.weights.range *= static_cast<float>(opt.lidar_weight);
    lo.weights.ret *= static_cast<float>(opt.lidar_weight);
    lo.weights.intensity *= static_cast<float>(opt.lidar_weight);
    lo.every = opt.lidar_every;
    lo.columns = opt.lidar_columns;
    lo.deterministic = opt.deterministic;
    absl::StatusOr<std::unique_ptr<LidarStage>> ls = LidarStage::Create(*opt.lidar_log, lo);
    if (!ls.ok()) return ls.status();
    lidar_stage = std::move(*ls);
  }

  bool said_suspicious = false;
  for (int64_t it = first; it <= opt.iterations; ++it) {
    const int active = std::min<int>(3, static_cast<int>(it / h.sh_degree_interval));
    const int vi = NextView(&st, num_views);
    const View& view = (*views)[vi];
    if (gt_cache[vi].empty()) gt_cache[vi] = view.RgbFloat();
    const std::vector<float>& gt = gt_cache[vi];
    // Densification, opacity reset and the Gaussians' lr schedule count from the stage's start.
    const bool fine = dynamic && it > static_its;
    const int64_t stage_it = fine ? it - static_its : it;
    if (fine && !stage) {
      absl::StatusOr<std::unique_ptr<DynamicStage>> b = DynamicStage::Begin(&st, fopt, fopt.time_range);
      if (!b.ok()) return b.status();
      stage = std::move(*b);
      guard.Rebaseline(it);
      if (absl::Status s = stage->OrderGaussians(&st, pool); !s.ok()) return s;
      LOG(INFO) << "iteration " << it << ": fine stage, field of " << stage->field().layout().total
                << " parameters";
    }
    GaussianParamsView params = ParamsView(st, active);
    if (fine) {
      absl::StatusOr<GaussianParamsView> d = stage->Deform(st, active, view.time_us, pool);
      if (!d.ok()) return d.status();
      params = *d;
    }
    if (absl::Status s = (*engine)->UpdateSceneParams(params, &scene); !s.ok()) return s;
    RenderOptions ro;
    ro.background = opt.sky ? Eigen::Vector3f(st.sky[0], st.sky[1], st.sky[2]) : Eigen::Vector3f::Zero();
    ro.keep_for_backward = true;
    const PinholeCamera camera =
        refine_poses ? CorrectedCamera(view.camera, ViewCorrection(st, vi)) : view.camera;
    if (absl::Status s = (*engine)->Render(*scene, camera, ro, &out); !s.ok()) return s;
    const int W = view.camera.width, H = view.camera.height;
    const size_t pixels = static_cast<size_t>(W) * H;

    // Exposure: out = A rgb + b per training image.
    const float* E = &st.exposure[static_cast<size_t>(vi) * 12];
    const std::vector<float>* image = &out.rgb;
    if (opt.exposure) {
      rgb_exp.resize(pixels * 3);
      for (size_t p = 0; p < pixels; ++p)
        for (int r = 0; r < 3; ++r)
          rgb_exp[p * 3 + r] = E[r * 4] * out.rgb[p * 3] + E[r * 4 + 1] * out.rgb[p * 3 + 1] +
                               E[r * 4 + 2] * out.rgb[p * 3 + 2] + E[r * 4 + 3];
      image = &rgb_exp;
    }
    d_rgb.assign(pixels * 3, 0.0f);
    d_depth.assign(pixels, 0.0f);
    // A grayscale camera beside colour ones supervises the render's luminance only (losses.h).
    const std::vector<float>* compared = image;
    float* d_compared = d_rgb.data();
    if (view.luminance_only) {
      luma.resize(pixels * 3);
      LuminanceRgb(image->data(), pixels, luma.data());
      d_luma.assign(pixels * 3, 0.0f);
      compared = &luma;
      d_compared = d_luma.data();
    }
    const double l1 = L1Loss(pool, compared->data(), gt.data(), pixels * 3, 1.0f, d_compared);
    const double ssim =
        Ssim(pool, compared->data(), gt.data(), W, H, static_cast<float>(-h.lambda_dssim), d_compared);
    if (view.luminance_only) LuminanceBackward(d_luma.data(), pixels, d_rgb.data());
    double ld = 0;
    if (opt.depth_loss) ld = DepthLoss(out.depth.data(), view.lidar, static_cast<float>(h.lambda_depth), d_depth.data());
    double loss = l1 + h.lambda_dssim * (1 - ssim) + h.lambda_depth * ld;
    const double psnr = Psnr(compared->data(), gt.data(), pixels * 3);

    // Back through the exposure to the render.
    const std::vector<float>* d_render = &d_rgb;
    if (opt.exposure) {
      d_pre.assign(pixels * 3, 0.0f);
      float dE[12] = {0};
      for (size_t p = 0; p < pixels; ++p) {
        for (int r = 0; r < 3; ++r) {
          const float g = d_rgb[p * 3 + r];
          for (int c = 0; c < 3; ++c) {
            dE[r * 4 + c] += g * out.rgb[p * 3 + c];
            d_pre[p * 3 + c] += E[r * 4 + c] * g;
          }
          dE[r * 4 + 3] += g;
        }
      }
      AdamStepSmall(&st.exposure[vi * 12], dE, &st.exposure_m[vi * 12], &st.exposure_v[vi * 12], 12, h.exposure_lr,
                    st.aux_step + 1);
      d_render = &d_pre;
    }
    if (opt.sky) {
      float dsky[3] = {0, 0, 0};
      for (size_t p = 0; p < pixels; ++p) {
        const float T = 1.0f - out.alpha[p];
        for (int c = 0; c < 3; ++c) dsky[c] += (*d_render)[p * 3 + c] * T;
      }
      AdamStepSmall(st.sky, dsky, st.sky_m, st.sky_v, 3, h.sky_lr, st.aux_step + 1);
    }
    st.aux_step += 1;

    BackwardOptions bo;
    bo.deterministic = opt.deterministic;
    RenderOutputGrads og;
    og.rgb = d_render->data();
    og.depth = opt.depth_loss ? d_depth.data() : nullptr;
    if (absl::Status s = (*engine)->RenderBackward(*scene, og, bo, &grads); !s.ok()) return s;
    // The pose from the camera's gradient alone (before the LiDAR step adds to the means').
    if (refine_poses && it > h.pose_refine_from && (h.pose_refine_until == 0 || it <= h.pose_refine_until))
      StepPoseCorrection(params, grads, camera, vi, h, pool, &st);
    // The LiDAR step before the field's backward: in the fine stage it renders the camera's
    // deformed means (the frame's time) and its means gradient joins the camera's, so that
    // DeformBackward chains the sum through the field.
    if (lidar_stage) {
      absl::StatusOr<double> lidar_loss =
          lidar_stage->Step(&st, view.frame, it, &grads, fine ? &stage->deformed_means() : nullptr);
      if (!lidar_loss.ok()) return lidar_loss.status();
      loss += *lidar_loss;
    }
    // Before the field's backward, which would spread one Gaussian's nan over the whole field.
    if (absl::Status s = GuardGradients(it, st.size(), kMaxNonFiniteGradientFraction, &grads, pool); !s.ok()) {
      return s;
    }
    if (fine && opt.motion_prior.weight > 0 && !motion_prior && !motion_prior_skipped) {
      const auto t0 = Clock::now();
      // Tracked in the training frames' scans only: held-out frames are never used.
      const DriveLog train_log =
          TrainingFramesLog(*opt.lidar_log, 0, static_cast<int>(opt.lidar_log->frames.size()), opt.holdout_every);
      absl::StatusOr<std::unique_ptr<MotionPrior>> mp = MotionPrior::Build(train_log, opt.motion_prior);
      if (!mp.ok() && !opt.motion_prior.optional) return mp.status();
      if (!mp.ok()) {
        LOG(WARNING) << "motion prior left out (the preset's; this log cannot carry it): " << mp.status().message();
        motion_prior_skipped = true;
      } else {
        motion_prior = std::move(*mp);
        motion_prior->Assign(st.params.means.data(), st.size(), pool);
        prior_rows_changed = false;
        LOG(INFO) << "motion prior: " << motion_prior->num_tracks() << " moving objects from "
                  << train_log.frames.size() << " training frames' LiDAR ("
                  << std::chrono::duration<double>(Clock::now() - t0).count() << " s), weight "
                  << opt.motion_prior.weight << ", " << MotionPriorScansName(opt.motion_prior.all_scans) << " scans; "
                  << motion_prior->assigned() << " of " << st.size() << " Gaussians on moving objects";
      }
    }
    if (fine && motion_prior) {
      if (prior_rows_changed || motion_prior->n() != st.size()) {
        motion_prior->Assign(st.params.means.data(), st.size(), pool);
        prior_rows_changed = false;
      }
      prior_grad.assign(st.size() * 3, 0.0f);
      loss += motion_prior->AddGradient(view.time_us, st.params.means.data(), stage->deformed_means().data(),
                                        prior_grad.data(), pool);
      for (size_t k = 0; k < prior_grad.size(); ++k) grads.means[k] += prior_grad[k];
    }
    if (fine) {
      absl::StatusOr<double> field_loss = stage->Backward(st, active, stage_it, &grads, *field_pool);
      if (!field_loss.ok()) return field_loss.status();
      loss += *field_loss;
    }
    // The prior depends on Δx alone: its identity path into the canonical means comes back out.
    if (fine && motion_prior) {
      for (size_t k = 0; k < prior_grad.size(); ++k) grads.means[k] -= prior_grad[k];
    }

    bool replaced = false;
    // Not on the last iteration: nothing would repair the fresh clones / split children / reset
    // opacities before the scene is written and evaluated (3DGS's runs end long after densify_until).
    if (stage_it < h.densify_until && it < opt.iterations) {
      AccumulateStats(&st, grads, W, H);
      if (stage_it > h.densify_from && stage_it % h.densify_interval == 0) {
        size_t added = 0, removed = 0;
        DensifyAndPrune(&st, h, stage_it, &added, &removed);
        if (fine) {
          if (absl::Status s = stage->OrderGaussians(&st, pool); !s.ok()) return s;
        }
        prior_rows_changed = true;
        LOG(INFO) << "iteration " << it << ": densified +" << added << " -" << removed << " -> " << st.size();
        replaced = true;
      }
      const bool outputs_soon = opt.write_outputs && opt.iterations - it < h.min_iterations_after_reset;
      if (stage_it % h.opacity_reset_interval == 0 && !outputs_soon) {
        ResetOpacity(&st);
        guard.Rebaseline(it);
        replaced = true;
      }
    }
    // On iterations that replace the Gaussian tensors, 3DGS's Adam sees no gradient for them.
    if (!replaced) AdamStepGaussians(&st, grads, active, stage_it, h, pool);
    st.iteration = it;

    recent_psnr.push_back(psnr);
    psnr_window += psnr;
    if (recent_psnr.size() > 50) {
      psnr_window -= recent_psnr.front();
      recent_psnr.erase(recent_psnr.begin());
    }
    recent_loss = recent_loss == 0 ? loss : 0.9 * recent_loss + 0.1 * loss;
    const double mean_psnr = psnr_window / recent_psnr.size();
    result.train_psnr_mean50 = mean_psnr;
    if (result.seconds_to_psnr24 < 0 && recent_psnr.size() >= 50 && mean_psnr >= 24) {
      result.seconds_to_psnr24 = SecondsSince(t_start);
    }
    if (it % 10 == 0 || it == opt.iterations) {
      st.curve.push_back(static_cast<double>(it));
      st.curve.push_back(recent_loss);
      st.curve.push_back(mean_psnr);
    }
    if (dynamic && it == static_its) {  // the fine stage's rate is measured from here
      rate_window.clear();
      rate_window.emplace_back(it, SecondsSince(t_loop));
    }
    if (progress && (it % 10 == 0 || it == opt.iterations || it == first)) {
      Progress p;
      p.iteration = it;
      p.total = opt.iterations;
      p.loss = loss;
      p.psnr = psnr;
      p.gaussians = st.size();
      const double now_s = SecondsSince(t_loop);
      if (rate_window.empty() || rate_window.back().first != it) rate_window.emplace_back(it, now_s);
      while (rate_window.size() > 11) rate_window.pop_front();  // ~100 iterations
      const auto& [it0, t0_s] = rate_window.front();
      p.it_per_s = it0 < it ? (it - it0) / std::max(now_s - t0_s, 1e-9) : (it - first + 1) / std::max(now_s, 1e-9);
      p.eta_static_stage_only = dynamic && it <= static_its;
      p.eta_s = ((p.eta_static_stage_only ? static_its : opt.iterations) - it) / std::max(p.it_per_s, 1e-9);
      progress(p);
    }
    const DivergenceGuard::Verdict verdict =
        opt.divergence_guard ? guard.Observe(it, loss, psnr) : DivergenceGuard::Verdict::kFine;
    if (verdict == DivergenceGuard::Verdict::kDiverged) {
      // No checkpoint of the diverged state: the last one on disk is from before it.
      log_fine_timings();
      absl::Status diverged = absl::AbortedError(absl::StrCat(
          "diverged at iteration ", it, fine ? " (fine stage)" : " (static stage)", ": ", guard.why(),
          "; the last checkpoint (iteration ", std::max<int64_t>(saved_iteration, first - 1), ") is from before"));
      diverged.SetPayload(kDivergedAtPayload, absl::Cord(absl::StrCat(it)));
      return diverged;
    }
    if (verdict == DivergenceGuard::Verdict::kSuspicious && !said_suspicious) {
      LOG(WARNING) << "iteration " << it << ": " << guard.why() << ": no checkpoint until it recovers";
    }
    said_suspicious = verdict == DivergenceGuard::Verdict::kSuspicious;
    if (opt.checkpoint_every > 0 && it % opt.checkpoint_every == 0 && verdict == DivergenceGuard::Verdict::kFine) {
      if (absl::Status s = save_checkpoint(); !s.ok()) return s;
    }
    if (opt.stop_requested != nullptr && opt.stop_requested->load(std::memory_order_relaxed)) {
      if (saved_iteration != st.iteration) {
        if (absl::Status s = save_checkpoint(); !s.ok()) return s;
      }
      log_fine_timings();
      return absl::CancelledError(absl::StrCat("stopped at iteration ", it, " of ", opt.iterations,
                                               ", checkpoint written: --resume continues from it"));
    }
    if (opt.stop_after > 0 && it >= opt.stop_after) {
      result.iterations = it;
      result.gaussians = st.size();
      result.seconds = SecondsSince(t_start);
      return result;
    }
  }

  // Final outputs.
  if (absl::Status s = save_checkpoint(); !s.ok()) return s;
  result.iterations = st.iteration;
  result.gaussians = st.size();
  log_fine_timings();
  if (lidar_stage && lidar_stage->steps() > 0) {
    LOG(INFO) << "LiDAR step: " << lidar_stage->steps() << " steps, "
              << lidar_stage->total_ms() / lidar_stage->steps() << " ms each";
  }
  if (opt.write_outputs) {
    // The learned LiDAR reflectance as an extra vertex property (lidar_eval.h reads it).
    const std::vector<float> reflectance = ReflectanceFromLogits(st.reflectance_logit);
    if (absl::Status s = WriteGaussianPly(st.params, (std::filesystem::path(out_dir) / "scene.ply").string(),
                                          st.reflectance_logit.empty() ? nullptr : &reflectance);
        !s.ok()) {
      return s;
    }
    nlohmann::json meta;
    meta["background"] = {opt.sky ? st.sky[0] : 0.0f, opt.sky ? st.sky[1] : 0.0f, opt.sky ? st.sky[2] : 0.0f};
    meta["resolution_scale"] = opt.resolution_scale;
    if (opt.low_res) {  // provenance: the run's first iterations were at this scale
      meta["low_res_scale"] = opt.low_res->resolution_scale;
      meta["low_res_iterations"] = opt.low_res->iterations;
    }
    meta["holdout_every"] = opt.holdout_every;
    meta["iterations"] = st.iteration;
    meta["gaussians"] = st.size();
    meta["extent_m"] = st.extent;
    meta["seed"] = opt.seed;
    meta["sky"] = opt.sky;
    meta["exposure"] = opt.exposure;
    meta["position_lr_decay_iterations"] = h.lr_decay_steps;  // the means' rate decay, per stage
    meta["densify_until"] = h.densify_until;                  // densification's end, per stage
    meta["field"] = !stage ? "static" : opt.field.extended ? "extended" : "s3gaussian";
    if (stage && opt.field.extended) {
      meta["field_modules"] = opt.field.extended->ModulesString();
      meta["field_ext_lr_scale"] = opt.field.ext_hyper.lr_scale;  // the extension's network rate
      meta["field_ext_lr_decay_iterations"] = opt.field.ext_hyper.lr_decay_steps;
    }
    if (stage && stage->extended() && stage->extension_from_fine_iteration() > 0) {
      meta["field_extension_from"] = stage->extension_from_fine_iteration();  // grown on a resume
    }
    if (stage && stage->extended() && stage->extended()->config().decoder) {
      // The trained field's own (a resumed stage keeps its checkpoint's): 0 = unbounded.
      meta["field_decoder_max_dlog_scale"] = stage->extended()->config().decoder_max_dlog_scale;
    }
    const std::string field_path = (std::filesystem::path(out_dir) / field::kFieldFileName).string();
    if (stage) {
      if (absl::Status s = stage->SyncHost(); !s.ok()) return s;  // the field's optimiser may be on the device
      meta["static_iterations"] = static_its;
      meta["field_lambda_dx"] = opt.field.hyper.lambda_dx;  // the Δ sparsity weights trained with
      meta["field_lambda_dsh"] = opt.field.hyper.lambda_dsh;
      meta["field_l1_time_planes"] = opt.field.hyper.l1_time_planes;
      meta["field_motion_prior"] = opt.motion_prior.weight;
      meta["field_motion_prior_scans"] = MotionPriorScansName(opt.motion_prior.all_scans);
      meta["field_lr_scale"] = opt.field.hyper.lr_scale;  // the field's learning-rate schedule
      meta["field_lr_decay_iterations"] = opt.field.hyper.lr_decay_steps;
      meta["field_time_resolution"] = stage->field().config().time_resolution;  // cells along time
      meta["time_range_us"] = {stage->field().time_range().start_us, stage->field().time_range().end_us};
      if (absl::Status s = field::SaveField(stage->field(), field_path); !s.ok()) return s;
    } else {
      std::filesystem::remove(field_path, ec);  // a static run replaces an earlier field scene
    }
    if (absl::Status s = checked_file::WriteAtomically((std::filesystem::path(out_dir) / "train_meta.json").string(),
                                                    meta.dump(2) + "\n");
        !s.ok()) {
      return s;
    }
    cv::Mat plot = PlotCurve(st.curve);
    if (absl::Status s = WriteRgbPng((std::filesystem::path(out_dir) / "curve.png").string(), plot); !s.ok()) return s;
    // The learned corrections of the training views; held-out views take them interpolated.
    std::vector<View> corrected_heldout;
    if (refine_poses) {
      const std::vector<PoseCorrection> corrections = TrainedCorrections(*views, st.pose_delta);
      if (absl::Status s = WritePoseCorrections(out_dir, corrections); !s.ok()) return s;
      LOG(INFO) << "pose corrections: " << CorrectionsSummary(corrections);
      if (!heldout.empty()) {
        corrected_heldout = heldout;
        ApplyPoseCorrections(corrections, &corrected_heldout);
      }
    } else {
      std::filesystem::remove(std::filesystem::path(out_dir) / kPoseCorrectionsFileName, ec);  // not this run's
    }
    // Held-out previews (render | ground truth) and metrics.
    if (!heldout.empty()) {
      const std::vector<View>* test = refine_poses ? &corrected_heldout : &heldout;
      const Eigen::Vector3f bg = opt.sky ? Eigen::Vector3f(st.sky[0], st.sky[1], st.sky[2]) : Eigen::Vector3f::Zero();
      // Each held-out view at its own time when there is a field.
      std::shared_ptr<const field::DeformationField> f;
      if (stage) f = stage->SceneField();
      absl::StatusOr<SceneForView> scene_for_view = MakeSceneForView(**engine, st.params, f);
      if (!scene_for_view.ok()) return scene_for_view.status();
      absl::StatusOr<EvalResult> ev = EvaluateViews(**engine, *scene_for_view, *test, bg);
      if (!ev.ok()) return ev.status();
      result.heldout = *ev;
      // Machine-readable beside the scene (the server's job record reads it; metrics_json.h).
      if (absl::Status s = WriteHeldoutMetrics(out_dir, result.heldout); !s.ok()) return s;
      const std::filesystem::path pdir = std::filesystem::path(out_dir) / "preview";
      std::filesystem::create_directories(pdir, ec);
      RenderOptions ro;
      ro.background = bg;
      const size_t step = std::max<size_t>(1, test->size() / 6);
      for (size_t i = 0; i < test->size(); i += step) {
        const View& v = (*test)[i];
        absl::StatusOr<const DeviceScene*> dev = (*scene_for_view)(v);
        if (!dev.ok()) return dev.status();
        if (absl::Status s = (*engine)->Render(**dev, v.camera, ro, &out); !s.ok()) return s;
        cv::Mat both;
        cv::hconcat(ToRgb8(out.rgb, v.camera.width, v.camera.height), v.rgb8, both);
        char name[64];
        std::snprintf(name, sizeof(name), "heldout_frame%04d_cam%d.png", v.frame, v.camera_obs);
        if (absl::Status s = WriteRgbPng((pdir / name).string(), both); !s.ok()) return s;
      }
    } else {
      std::filesystem::remove(std::filesystem::path(out_dir) / kHeldoutMetricsFileName, ec);  // not this run's
    }
  }
  result.seconds = SecondsSince(t_start);
  return result;
}

}  // namespace streetsim::train
