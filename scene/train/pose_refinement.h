// Camera pose refinement: a learned rigid correction per training view, optimised with the scene.
//
// The log's camera poses are LiDAR registration (KITTI: ICP without GNSS) and carry errors the
// images contradict: centimetre jumps between frames and a 0.33 degree turn of the standing car at
// the light (docs/field.md "What limits held-out PSNR"). A scene trained on them blurs what the
// poses misplace. Each training view gets a correction E = [R(w), v] in its camera frame,
// T_world_from_cam' = T_world_from_cam * E, learned by Adam from the render's gradient.
//
// The gradient needs no kernel of its own: moving the camera by a small rigid motion renders the
// same image as moving every Gaussian by the inverse motion, so dL/dE follows exactly from the
// per-Gaussian gradients any backend's RenderBackward returns (means and rotations; see
// PoseGradient for the one approximation, the SH view direction).
//
// Held-out views are not trained; they take the corrections of the same camera's nearest training
// views before and after them, interpolated in time (the refined trajectory, from training data
// only). DIR/pose_corrections.json carries the training views' corrections for `streetsim eval`.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/train/dataset.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

inline constexpr char kPoseCorrectionsFileName[] = "pose_corrections.json";

// (w_x, w_y, w_z) rotation vector in radians, then (v_x, v_y, v_z) translation in metres, both in
// the camera frame (x right, y down, z forward).
using PoseDelta = std::array<float, 6>;

struct PoseCorrection {
  int frame = 0;
  int camera_obs = 0;
  int64_t time_us = 0;
  PoseDelta delta{};
};

// The camera moved by the correction: T_world_from_cam * [R(w), v].
PinholeCamera CorrectedCamera(const PinholeCamera& camera, const PoseDelta& delta);

// dL/d(delta) of the view just rendered with CorrectedCamera(camera, delta), from the gradients of
// the Gaussians it rendered (`rendered`: the uploaded parameters, deformed ones in a field's fine
// stage; `grads`: RenderBackward's, before anything else adds to them). Exact for everything that
// depends on where the Gaussians sit in the camera frame (projection, covariance, depth); the SH
// colours' view direction is treated as moving with the Gaussians, which a camera turn does not do
// (exact at SH degree 0, a bias from view-dependent colour otherwise: the rotation part's magnitude
// 12% low on grad_check's random scenes, whose SH are far more view-dependent than a trained
// street's; the translation part is exact at every degree).
PoseDelta PoseGradient(const GaussianParamsView& rendered, const GaussianGrads& grads,
                       const PinholeCamera& corrected_camera, const PoseDelta& delta, ThreadPool& pool);

// The trainer's side. Sizes the state's corrections for `num_views` (zero when it has none: a new
// run, or one that starts refining here); FailedPrecondition when it has them for another count.
absl::Status PreparePoseCorrections(int num_views, TrainState* st);
// The state's correction of training view `view`.
PoseDelta ViewCorrection(const TrainState& st, int view);
// One Adam step of the view's correction (Hyper's pose rates, the view's own step count) from the
// render's gradients, as PoseGradient takes them. A non-finite gradient skips the step.
void StepPoseCorrection(const GaussianParamsView& rendered, const GaussianGrads& grads,
                        const PinholeCamera& corrected_camera, int view, const Hyper& h, ThreadPool& pool,
                        TrainState* st);

// The training views' corrections from a run's state ([views * 6], the views' order).
std::vector<PoseCorrection> TrainedCorrections(const std::vector<View>& views, const std::vector<float>& pose_delta);

// "N views, rotation mean A / max B deg, translation mean C / max D cm", for the run's log.
std::string CorrectionsSummary(const std::vector<PoseCorrection>& corrections);

// The correction of every view in `views` (same order): a training view's own from `trained`, a
// view without one (held out) interpolated in time between the same camera's nearest trained views
// before and after it (the nearest one at the ends; zero when the camera has none).
std::vector<PoseDelta> CorrectionsForViews(const std::vector<PoseCorrection>& trained, const std::vector<View>& views);

// Moves each view's camera by CorrectionsForViews.
void ApplyPoseCorrections(const std::vector<PoseCorrection>& trained, std::vector<View>* views);

// DIR/pose_corrections.json, atomically: {"corrections": [{"frame", "camera_obs", "time_us",
// "rotation_rad": [3], "translation_m": [3]}], "max_rotation_deg", "max_translation_m"}.
absl::Status WritePoseCorrections(const std::string& dir, const std::vector<PoseCorrection>& corrections);
// Back. NotFound without the file; DataLoss naming it when malformed or not finite.
absl::StatusOr<std::vector<PoseCorrection>> ReadPoseCorrections(const std::string& dir);

}  // namespace streetsim::train
