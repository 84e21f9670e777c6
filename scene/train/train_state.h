// The whole state of a static-stage training run (S3Gaussian coarse stage,
// ../shared/docs/s3gaussian-spec.md sections 2, 6, 7): Gaussians, Adam moments, densification
// statistics, the learned background and per-image exposure, the view queue and the RNG; plus
// the pieces that act on it: Adam with the spec's parameter groups and schedules, densification
// (clone / split / prune) and opacity reset, and checkpoints (written atomically).
#pragma once

#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim::train {

inline constexpr int kMaxDensifyUntil = 10'000'000;

struct Hyper {
  // Adam (section 6): eps 1e-15, betas (0.9, 0.999).
  double xyz_lr_init = 1.6e-4, xyz_lr_final = 1.6e-6;  // times the scene extent E
  // The means' exponential decay, in iterations of the stage (a field run's fine stage counts from
  // its own start): 3DGS's 30 000; shorter anneals a resumed run (--position-lr-decay-iterations).
  int lr_decay_steps = 30000;
  double f_dc_lr = 2.5e-3, f_rest_lr = 2.5e-3 / 20, opacity_lr = 0.05, scaling_lr = 5e-3, rotation_lr = 1e-3;
  double sky_lr = 1e-2, exposure_lr = 1e-3;  // streetsim's additions (not in S3Gaussian)
  // Camera pose refinement (streetsim's, pose_refinement.h): Adam rates of the per-view rotation
  // (rad) and translation (m); the first pose_refine_from iterations leave the poses alone, so
  // that a coarse scene does not pull them; after pose_refine_until (0: never) they stay as they
  // are (e.g. the static stage's, for a field that would otherwise compete with them).
  double pose_rotation_lr = 3e-4, pose_translation_lr = 3e-3;
  int pose_refine_from = 300;
  int64_t pose_refine_until = 0;
  // Losses (section 5).
  double lambda_dssim = 0.2, lambda_depth = 0.5;
  // Densification (section 7), counted in iterations of the stage. densify_until also ends the
  // opacity resets; a run can end it early (--densify-until) to polish a fixed set of Gaussians,
  // as 3DGS's last 15 000 iterations do.
  int densify_from = 500, densify_until = 25000, densify_interval = 100, opacity_reset_interval = 3000;
  // streetsim's: no opacity reset within this many iterations of the run's written outputs. A reset
  // sets every opacity to at most 0.01 and the scene needs hundreds of iterations to recover (KITTI
  // field run: 17.0 dB held-out 10 iterations after the reset at fine iteration 3000, 25.6 after
  // 510); the spec's runs end long after densify_until, runs cut to a budget can end anywhere.
  int min_iterations_after_reset = 500;
  double densify_grad_threshold = 0.0002, percent_dense = 0.01, min_opacity = 0.005;
  size_t max_gaussians = 2'000'000;
  int sh_degree_interval = 1000;
};

struct TrainState {
  int64_t iteration = 0;  // completed iterations
  double extent = 1.0;    // scene extent E (1.1 x max training camera distance from their mean)
  GaussianStore params;   // sh_degree 3
  GaussianStore adam_m, adam_v;
  int64_t adam_step = 0;
  // max_radii: the largest screen radius since the last densification step; kept in checkpoints,
  // not a prune criterion (DensifyAndPrune says why).
  std::vector<float> grad_accum, denom, max_radii;
  float sky[3] = {0, 0, 0}, sky_m[3] = {0, 0, 0}, sky_v[3] = {0, 0, 0};
  int64_t aux_step = 0;  // Adam step of sky / exposure
  std::vector<float> exposure, exposure_m, exposure_v;  // [views * 12]: 3x3 row-major, then bias
  std::vector<int> view_queue;
  std::mt19937_64 rng;
  // Curve: (iteration, loss, psnr) every few iterations, for the plot.
  std::vector<double> curve;
  // LiDAR reflectance (lidar_stage.h): per-Gaussian logit (reflectance = sigmoid(logit)) and its
  // Adam moments and step; empty when the run has no LiDAR loss. Clone / split / prune and
  // checkpoints (a trailing optional section) carry them.
  std::vector<float> reflectance_logit, reflectance_m, reflectance_v;
  int64_t reflectance_step = 0;
  // Camera pose refinement (pose_refinement.h): per training view a correction (rotation vector,
  // translation; PoseDelta) and its Adam moments, [views * 6]; empty when the run does not refine
  // poses (checkpoints: another trailing optional section). pose_steps: each view's Adam step
  // (a view is updated only when it is drawn, about once per views iterations).
  std::vector<float> pose_delta, pose_m, pose_v;
  std::vector<int64_t> pose_steps;

  // Identity-initialised state for the given Gaussians (raised to SH degree 3).
  static TrainState Init(const GaussianStore& init, double extent, int num_views, uint64_t seed);
  size_t size() const { return params.size(); }
};

// The store to render at an active SH degree (a copy of the parameters, fewer SH coefficients).
void RenderStore(const TrainState& s, int active_degree, GaussianStore* out);

// The parameters at an active SH degree as a view for Engine::UpdateSceneParams (no copy).
GaussianParamsView ParamsView(const TrainState& s, int active_degree);

double ExpLr(double init, double final_lr, int64_t step, int max_steps);

// One Adam step of every Gaussian parameter with the spec's groups (lr at `iteration`). `grads`
// holds the rendered scene's gradients (SH for `active_degree` only).
void AdamStepGaussians(TrainState* s, const GaussianGrads& grads, int active_degree, int64_t iteration,
                       const Hyper& h, ThreadPool& pool);
// Adam on a small array (sky, exposure).
void AdamStepSmall(float* p, const float* g, float* m, float* v, size_t n, double lr, int64_t step);

// Densification statistics of one rendered view (visible = radii > 0).
void AccumulateStats(TrainState* s, const GaussianGrads& grads, int width, int height);
// Clone / split (when N < max) then prune (section 7). Returns the number added / removed.
void DensifyAndPrune(TrainState* s, const Hyper& h, int64_t iteration, size_t* added, size_t* removed);
// Reorders the Gaussians: row r becomes old row order[r] in every per-Gaussian array (parameters,
// Adam moments, densification statistics, reflectance). The field's passes keep the Gaussians in
// a spatial order with it (DynamicStage::OrderGaussians). InvalidArgument unless `order` is a
// permutation of the rows.
absl::Status PermuteRows(TrainState* s, const std::vector<uint32_t>& order);
// opacity = logit(min(sigmoid(opacity), 0.01)); opacity moments zeroed.
void ResetOpacity(TrainState* s);

absl::Status SaveCheckpoint(const TrainState& s, const std::string& path);
absl::StatusOr<TrainState> LoadCheckpoint(const std::string& path);
// The iteration a checkpoint was written at, from its header alone (the CLI's --field default
// on resume reads it without loading the Gaussians). DataLoss when the file is not a checkpoint.
absl::StatusOr<int64_t> PeekCheckpointIteration(const std::string& path);

}  // namespace streetsim::train
