// S3Gaussian's fine stage (../shared/docs/s3gaussian-spec.md 3.3, 5, 6, 7, 8; docs/training.md
// "Dynamic field"): the deformation field (scene/field) trained jointly with the Gaussians after
// the static stage. The trainer calls, per fine iteration:
//   Deform (view time -> field -> deformed parameters to upload) -> render, loss, RenderBackward
//   -> Backward (field gradient + regularisers + field Adam; grads become canonical) -> the
//   Gaussians' densification and Adam as in the static stage, with the stage's iteration counter.
// Also: the field's part of checkpoints, and rendering a trained scene at a view's time.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/deformed_scene.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/field_adam.h"
#include "render/vulkan/field/vulkan_field_device.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/train/dataset.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

enum class FieldMode { kStatic, kS3Gaussian };
enum class FieldDevice { kAuto, kCpu, kVulkan };
enum class FieldOptimizerPlace { kAuto, kDevice, kHost };
absl::StatusOr<FieldDevice> ParseFieldDevice(const std::string& text);
// "auto" | "device" | "host" (--field-optimizer).
absl::StatusOr<FieldOptimizerPlace> ParseFieldOptimizerPlace(const std::string& text);
// kAuto -> kVulkan when `backend` is vulkan and a Vulkan GPU exists, else kCpu.
FieldDevice ResolveFieldDevice(FieldDevice device, Backend backend);
const char* FieldModeName(FieldMode mode);
absl::StatusOr<FieldMode> ParseFieldMode(const std::string& text);

struct FieldOptions {
  FieldMode mode = FieldMode::kStatic;
  // Length of the static (coarse) stage; the fine stage runs iterations - static_iterations.
  int static_iterations = 5000;
  field::FieldConfig config;  // streetsim's default: the spec's sizes, time over the full [-1, 1]
  field::FieldHyper hyper;    // the spec's learning rates and loss weights
  // The log's time range (the field's time axis; Train sets it from the log's first and last
  // frame). Both 0: TrainOnViews takes the range of its training and held-out views' times.
  field::FieldTimeRange time_range;
  uint64_t seed = 0;  // field initialisation (added to TrainOptions::seed)
  // Clips (clip_training.h, docs/training.md "Clips"): the previous clip's field, whose parameters
  // start the fine stage instead of the spec init (spec 8's prior checkpoint). The AABB (of this
  // run's Gaussians) and the time range stay this run's. Must have `config`'s layout.
  std::shared_ptr<const field::DeformationField> prior;
  // --field extended (docs/field.md "Extended field"): the seed paper's modules on top of the
  // field above (set: the fine stage trains an ExtendedField; its base is what `config`, `prior`
  // and field.bin describe). The extension's parameters start from their init, or from ext_prior's.
  std::optional<field::ExtendedFieldConfig> extended;
  // Clips with --field extended: the previous clip's extension (field_ext.bin, loaded against its
  // field.bin), whose parameters start this fine stage's extension; it must have `extended`'s
  // modules and sizes. Its Adam moments and the KL warm-up are not carried over (a fresh Adam and
  // schedules per clip, like the base field's).
  std::shared_ptr<const field::ExtendedField> ext_prior;
  field::ExtHyper ext_hyper;  // the extension's Adam group ("network", lr 1.6e-3)
  // Resume only (docs/training.md "Growing modules on a trained field"): the checkpoint is an
  // S3Gaussian run's and `extended`'s modules join it at their init (every module's output enters
  // through a zero gate or a zero last layer, so the field renders as the checkpoint did), with a
  // fresh Adam. The caller sets it only where checkpoint.json says the run is S3Gaussian's, so a
  // lost extension file is refused rather than silently re-initialised.
  bool grow_extension = false;
  // The fine iteration an extended run's modules joined at (checkpoint.json; 0: from the start of
  // the fine stage): the extension's Adam has done the fine iterations since.
  int64_t extension_from_fine_iteration = 0;
  // The log's frame interval: the token window's Δ is one frame on the time axis (0: keep
  // extended->window_dt as given).
  int64_t frame_interval_us = 0;
  // Where S3Gaussian's field runs in the fine stage (docs/field.md "Vulkan field"): kAuto takes
  // the Vulkan field when the trainer's backend is vulkan and a Vulkan GPU exists (on lavapipe it
  // is 20-40x slower than the cpu field; ResolveFieldDevice); kVulkan forces it (any Vulkan
  // device). The same holds for --field extended (field::VulkanFieldDevice makes the kernels of
  // either field; docs/field.md "Extended field on Vulkan").
  FieldDevice device = FieldDevice::kAuto;
  // With S3Gaussian's field on Vulkan, where its plane regularisers and Adam run. kDevice: there
  // too (VulkanField::RegularizeAndStep, the host's formulas), so that the gradient and the
  // parameters (143 MB each at spec sizes) stay on the device; the host copy is read back for
  // checkpoints and the end of the run. kHost: the gradient is downloaded, stepped on the host and
  // the parameters uploaded every iteration. kAuto: kDevice on a GPU, kHost on a CPU Vulkan device
  // (lavapipe runs these parameter-sized passes ~9x slower than the host's vectorised loops,
  // docs/benchmarks.md "Field optimiser on the device").
  FieldOptimizerPlace optimizer = FieldOptimizerPlace::kAuto;
};

// The field's AABB from the canonical Gaussians at the start of the fine stage: their bounding
// box (S3Gaussian takes the LiDAR cloud's), padded 1 % (at least 1 cm) on every axis.
field::FieldAabb AabbOfMeans(const std::vector<float>& means);

// Where a fine iteration's time goes (milliseconds summed over `iterations`), printed at the end of
// a run: on a GPU the field's own kernels are a small part of it (docs/benchmarks.md "Vulkan on a
// GPU"); the host-side regularisers, Adam and the parameter upload are what to move next.
struct FineStageTimings {
  int64_t iterations = 0;
  double deform_ms = 0;        // the field's forward for the view (and the deformed scene)
  double backward_ms = 0;      // the field's backward, its gradients on the host
  double regularizers_ms = 0;  // plane TV / time smoothness / time-plane L1 (host)
  double adam_ms = 0;          // the field's Adam (host)
  double gradient_check_ms = 0;  // the non-finite check of the networks' gradients before Adam (host)
  double upload_ms = 0;        // the stepped parameters back to the device (Vulkan field)
  // The optimiser on the device (FieldOptions::optimizer): regularizers_ms is 0 and adam_ms holds the
  // device's regularisers + Adam.
  bool optimizer_on_device = false;
  std::string Summary() const;  // one line, ms per iteration
};

class DynamicStage {
 public:
  // Starts the fine stage on `st`: a new field over the Gaussians' AABB and a fresh field Adam;
  // the Gaussians' Adam moments and densification statistics are re-created (spec 6: the
  // optimiser and every schedule restart per stage).
  static absl::StatusOr<std::unique_ptr<DynamicStage>> Begin(TrainState* st, const FieldOptions& options,
                                                             const field::FieldTimeRange& time_range);
  // The fine stage of a checkpoint (SaveCheckpoint's file); `fine_iterations` is what the
  // Gaussian checkpoint says has been done (checked against the field Adam's step).
  static absl::StatusOr<std::unique_ptr<DynamicStage>> Resume(const std::string& path, const FieldOptions& options,
                                                              int64_t fine_iterations);
  absl::Status SaveCheckpoint(const std::string& path);  // after SyncHost
  // With the optimiser on the device (FieldOptions::optimizer): reads the field's
  // parameters and Adam moments back into the host copy that field(), SceneField() and the
  // checkpoints use. A no-op when the host copy is current.
  absl::Status SyncHost();

  // Sorts the Gaussians' rows along a Morton curve of their canonical means in the field's AABB
  // (field::SpatialOrder, train::PermuteRows): neighbouring rows then sample neighbouring texels,
  // which makes the field's passes 15-20 % cheaper on a trained KITTI scene than the trainer's own
  // order (LiDAR init, then densification's clones appended; docs/field.md "Speed"). The trainer
  // calls it when the fine stage begins and after every densification in it, so the order is part
  // of the checkpointed state and a resumed run continues exactly.
  absl::Status OrderGaussians(TrainState* st, ThreadPool& pool) const;

  // The parameters to upload for a view at `time_us`: canonical, with deformed means and SH.
  absl::StatusOr<GaussianParamsView> Deform(const TrainState& st, int active_degree, int64_t time_us,
                                            ThreadPool& pool);
  // After RenderBackward of the scene Deform returned (same Gaussians): adds the field's gradient
  // (+ Δ sparsity), the plane regularisers, steps the field's Adam at fine iteration
  // `fine_iteration` (1-based), and turns grads->means into canonical-mean gradients. Returns the
  // loss terms it added (weighted).
  absl::StatusOr<double> Backward(const TrainState& st, int active_degree, int64_t fine_iteration,
                                  GaussianGrads* grads, ThreadPool& pool);

  // The base field (planes, S3Gaussian's MLP; field.bin) also with --field extended. With the
  // optimiser on the device this host copy is current after SyncHost only.
  const field::DeformationField& field() const { return ext_ ? ext_->base() : field_; }
  // The extended field (null without --field extended).
  const field::ExtendedField* extended() const { return ext_.get(); }
  // The trained field as render / eval take it (an extended field travels with its base,
  // field::ShareWithExtension). A copy.
  std::shared_ptr<const field::DeformationField> SceneField() const;
  // The means of the last Deform (what the camera rendered; the LiDAR step renders them too).
  const std::vector<float>& deformed_means() const { return ext_ ? ext_deformed_.means : deformed_.means; }
  const FineStageTimings& timings() const { return timings_; }
  // FieldOptions::extension_from_fine_iteration as this stage runs it (a grown extension: the
  // iteration it was grown at), for checkpoint.json.
  int64_t extension_from_fine_iteration() const { return extension_from_; }

 private:
  DynamicStage(field::DeformationField f, field::FieldAdamState adam, const FieldOptions& options);
  field::DeformationField field_;
  field::FieldAdamState adam_;
  field::FieldHyper hyper_;
  std::unique_ptr<field::FieldWorkspace> ws_;
  field::DeformedScene deformed_;
  std::vector<float> d_field_;
  // The field on Vulkan (FieldOptions::device; S3Gaussian's or the extended one, as the server's
  // served scenes have it), created at the first Deform from the field's parameters and
  // re-uploaded after every Adam step on the host.
  bool use_vulkan_ = false;
  std::unique_ptr<field::VulkanFieldDevice> vk_;
  FieldOptimizerPlace optimizer_place_;  // FieldOptions::optimizer
  bool optimizer_on_device_ = false;     // what it resolved to for vk_
  bool host_stale_ = false;           // vk_ holds newer parameters / moments than field_ / adam_
  std::vector<float> vk_scratch_;
  FineStageTimings timings_;
  absl::StatusOr<GaussianParamsView> DeformBase(const TrainState& st, int active_degree, int64_t time_us,
                                                ThreadPool& pool);
  // --field extended (field_ is moved into ext_).
  absl::StatusOr<GaussianParamsView> DeformExtended(const TrainState& st, int active_degree, int64_t time_us,
                                                    ThreadPool& pool);
  // S3Gaussian's field on Vulkan with its optimiser there (FieldOptions::optimizer).
  absl::StatusOr<double> BackwardOnDevice(const TrainState& st, int active_degree, int64_t fine_iteration,
                                          GaussianGrads* grads, ThreadPool& pool);
  absl::StatusOr<double> BackwardExtended(const TrainState& st, int active_degree, int64_t fine_iteration,
                                          GaussianGrads* grads, ThreadPool& pool);
  std::unique_ptr<field::ExtendedField> ext_;
  field::ExtEvaluator ext_eval_;  // vk_'s forward / backward of the extended field (empty: the cpu)
  field::ExtAdamState ext_adam_;
  field::ExtHyper ext_hyper_;
  std::unique_ptr<field::ExtWorkspace> ext_ws_;
  field::ExtDeformedScene ext_deformed_;
  std::vector<float> d_ext_;
  uint64_t ext_noise_seed_ = 0;
  int64_t ext_deforms_ = 0;  // ε of the VAE: a new draw per fine iteration
  int64_t extension_from_ = 0;
  // Moves field_ into a new ext_ with options.extended's modules at their init (or, from_prior,
  // the previous clip's parameters).
  absl::Status AttachExtension(const FieldOptions& options, bool from_prior);
};

// The extension's fine-stage checkpoint beside FieldCheckpointPath's file (checkpoint_field_N_ext.bin).
std::string ExtendedCheckpointPath(const std::string& field_checkpoint_path);

// Fine-stage checkpoint of the field beside the Gaussian checkpoint: one file per iteration (so
// that a crash between the two writes never pairs a field with the wrong Gaussians).
std::string FieldCheckpointPath(const std::string& out_dir, int64_t iteration);
// Removes the directory's field checkpoints other than `keep_iteration`'s (-1: all).
void RemoveFieldCheckpoints(const std::string& out_dir, int64_t keep_iteration);
// Which field checkpoints a run directory holds: S3Gaussian's (checkpoint_field_N.bin) and the
// extension's (checkpoint_field_N_ext.bin) — how the CLI tells a run's field on --resume.
struct FieldCheckpointsFound {
  bool base = false, extended = false;
};
FieldCheckpointsFound FindFieldCheckpoints(const std::string& out_dir);

// The scene to render for a view: canonical (static scene) or deformed at the view's time.
using SceneForView = std::function<absl::StatusOr<const DeviceScene*>(const View&)>;
// A SceneForView of `canonical` (SH degree 3 for a field) and an optional field. Keeps its own
// upload; valid while the engine is.
absl::StatusOr<SceneForView> MakeSceneForView(Engine& engine, const GaussianStore& canonical,
                                              std::shared_ptr<const field::DeformationField> field);

// The store of `canonical` deformed by `field` at `time_us` (clamped to the field's time range).
absl::StatusOr<GaussianStore> DeformedStore(const field::DeformationField& field, const GaussianStore& canonical,
                                            int64_t time_us, ThreadPool& pool);

// The store to render at a time (lidar_eval.h StoreAtTime): `canonical` deformed by `field` as
// DeformedStore does (valid while `canonical` is); an empty function when `field` is null.
std::function<absl::StatusOr<GaussianStore>(int64_t time_us)> MakeStoreAtTime(
    std::shared_ptr<const field::DeformationField> field, const GaussianStore& canonical);

// DIR/field.bin when present (nullptr when the scene is static).
absl::StatusOr<std::shared_ptr<const field::DeformationField>> LoadSceneField(const std::string& dir);

}  // namespace streetsim::train
