#include "scene/train/config/train_settings.h"

#include <string>

#include "absl/strings/str_cat.h"
#include "scene/field/extended/extended_config.h"
#include "scene/train/clips.h"
#include "scene/train/motion_prior.h"
#include "scene/train/resolution_schedule.h"

namespace streetsim::train::config {
namespace {

using T = SettingType;
using G = SettingGroup;
using V = SettingValue;

int64_t I(const V& v) { return std::get<int64_t>(v); }
double D(const V& v) { return std::get<double>(v); }
bool B(const V& v) { return std::get<bool>(v); }
const std::string& S(const V& v) { return std::get<std::string>(v); }

absl::Status CheckModules(const std::string& text) {
  return field::ExtendedFieldConfig::WithModules(text).status();
}

constexpr double kMaxIterations = 10'000'000;

// The table. Defaults are the trainer's own where a preset does not set them; the measured best
// lives in the presets (presets/*.json), which set what differs.
std::vector<SettingDef> MakeDefs() {
  std::vector<SettingDef> d;
  auto add = [&](SettingDef def) { d.push_back(std::move(def)); };
  // --- common ---
  add({.name = "iterations", .type = T::kInt, .default_value = int64_t{30000}, .min = 1, .max = kMaxIterations,
       .group = G::kCommon, .help = "training iterations in all (static stage and fine stage)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.iterations = static_cast<int>(I(v)); }});
  add({.name = "resolution-scale", .type = T::kDouble, .default_value = 1.0, .min = 0, .max = 1,
       .min_exclusive = true, .group = G::kCommon, .help = "image scale the run trains and evaluates at",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.resolution_scale = D(v); }});
  add({.name = "field", .type = T::kChoice, .default_value = std::string("auto"),
       .choices = {"auto", "static", "s3gaussian", "extended"}, .group = G::kCommon,
       .help = "the scene's time-dependent field; auto: S3Gaussian's when the run is longer than its static "
               "stage and the log has LiDAR, else static; extended: S3Gaussian's with the seed paper's modules",
       .apply = nullptr});
  add({.name = "static-iterations", .type = T::kInt, .default_value = int64_t{5000}, .min = 0, .max = kMaxIterations,
       .group = G::kCommon, .help = "the static stage before the field (below iterations)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.static_iterations = static_cast<int>(I(v)); }});
  add({.name = "holdout-every", .type = T::kInt, .default_value = int64_t{4}, .min = 0, .max = 1'000'000,
       .group = G::kCommon, .help = "every K-th frame held out for evaluation (0: none; 1 is refused)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.holdout_every = static_cast<int>(I(v)); }});
  add({.name = "seed", .type = T::kInt, .default_value = int64_t{0}, .min = 0, .max = 9'007'199'254'740'991.0,
       .group = G::kCommon, .help = "random seed (view order, init, field init)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.seed = static_cast<uint64_t>(I(v)); }});
  add({.name = "checkpoint-every", .type = T::kInt, .default_value = int64_t{1000}, .min = 0, .max = kMaxIterations,
       .group = G::kCommon, .help = "write a checkpoint every N iterations (0: only at stage ends)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.checkpoint_every = static_cast<int>(I(v)); }});
  add({.name = "backend", .type = T::kChoice, .default_value = std::string("cpu"), .choices = {"cpu", "vulkan", "auto"},
       .group = G::kCommon, .help = "the renderer's backend (auto: cpu)",
       .apply = [](const V& v, TrainRunOptions* o) {
         o->train.backend = S(v) == "vulkan" ? Backend::kVulkan : Backend::kCpu;
       }});
  add({.name = "pose-refinement", .type = T::kBool, .default_value = false, .group = G::kCommon,
       .help = "learn a pose correction per training view",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.pose_refinement = B(v); }});
  add({.name = "field-motion-prior", .type = T::kDouble, .default_value = 0.0, .min = 0, .max = kMaxMotionPriorWeight,
       .group = G::kCommon, .help = "weight of the LiDAR motion prior on the field's Δx (0: off; needs LiDAR)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.motion_prior.weight = D(v); }});
  add({.name = "clip-frames", .type = T::kInt, .default_value = int64_t{0}, .min = 0, .max = 1'000'000,
       .group = G::kCommon, .help = "clips of N frames chained through the field (0: one clip)",
       .apply = [](const V& v, TrainRunOptions* o) { o->clips.clip_frames = static_cast<int>(I(v)); }});
  add({.name = "lidar-loss", .type = T::kBool, .default_value = true, .group = G::kCommon,
       .help = "the LiDAR losses in the static stage (--no-lidar-loss: off)", .apply = nullptr});
  add({.name = "sky", .type = T::kBool, .default_value = true, .group = G::kCommon,
       .help = "a learned background colour (--no-sky: black)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.sky = B(v); }});
  add({.name = "depth", .type = T::kBool, .default_value = true, .group = G::kCommon,
       .help = "the LiDAR depth loss on the camera render (--no-depth: off)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.depth_loss = B(v); }});
  add({.name = "grayscale-cameras", .type = T::kChoice, .default_value = std::string("luminance"),
       .choices = {"luminance", "skip", "as-colour"}, .group = G::kCommon,
       .help = "grayscale cameras in a log with colour ones: trained and measured on luminance, left out, or "
               "trained as colour targets (a log of grayscale cameras only trains them as they are)",
       .apply = [](const V& v, TrainRunOptions* o) {
         o->train.grayscale_cameras = S(v) == "skip"        ? GrayscaleCameras::kSkip
                                      : S(v) == "as-colour" ? GrayscaleCameras::kAsColour
                                                            : GrayscaleCameras::kLuminance;
       }});
  add({.name = "exposure", .type = T::kBool, .default_value = false, .group = G::kCommon,
       .help = "a learned affine colour per training image",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.exposure = B(v); }});
  // --- advanced ---
  add({.name = "deterministic", .type = T::kBool, .default_value = false,
       .help = "fixed-order gradient sums (the same bits run to run; slower)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.deterministic = B(v); }});
  // Read by the run's end (client/cli/train_command.cc), not by the trainer: no apply.
  add({.name = "actors", .type = T::kBool, .default_value = true, .group = G::kCommon,
       .help = "at the end of the run, the log's moving objects (followed in its LiDAR) become actors a scenario can "
               "remove, move or copy: DIR/actors.json (docs/actors.md); a log without LiDAR has none"});
  add({.name = "divergence-guard", .type = T::kBool, .default_value = true,
       .help = "when the training loss diverges, go back to the last good checkpoint and lower the field's rates "
               "(docs/training.md \"Divergence guard\")",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.divergence_guard = B(v); }});
  add({.name = "voxel", .type = T::kDouble, .default_value = 0.15, .min = 0, .max = 100, .min_exclusive = true,
       .help = "LiDAR init voxel size, metres",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.init_voxel_m = D(v); }});
  add({.name = "densify-until", .type = T::kInt, .default_value = int64_t{25000}, .min = 0, .max = kMaxDensifyUntil,
       .help = "densification and opacity resets run until this iteration of a stage",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.hyper.densify_until = static_cast<int>(I(v)); }});
  add({.name = "position-lr-decay-iterations", .type = T::kInt, .default_value = int64_t{30000}, .min = 1,
       .max = kMaxIterations, .help = "the Gaussian means' rate decays over N iterations of a stage",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.hyper.lr_decay_steps = static_cast<int>(I(v)); }});
  add({.name = "low-res-scale", .type = T::kDouble, .default_value = 0.25, .min = 0, .max = 1, .min_exclusive = true,
       .help = "the low-resolution first stage's scale (with low-res-iterations)", .apply = nullptr});
  add({.name = "low-res-iterations", .type = T::kInt, .default_value = int64_t{0}, .min = 0, .max = kMaxIterations,
       .help = "the first N iterations at low-res-scale (0: none)", .apply = nullptr});
  add({.name = "pose-lr-scale", .type = T::kDouble, .default_value = 1.0, .min = 0, .max = 1000, .min_exclusive = true,
       .help = "pose refinement's rates x S",
       .apply = [](const V& v, TrainRunOptions* o) {
         o->train.hyper.pose_rotation_lr *= D(v);
         o->train.hyper.pose_translation_lr *= D(v);
       }});
  add({.name = "pose-refine-from", .type = T::kInt, .default_value = int64_t{300}, .min = 0, .max = kMaxIterations,
       .help = "pose corrections move from this iteration",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.hyper.pose_refine_from = static_cast<int>(I(v)); }});
  add({.name = "pose-refine-until", .type = T::kInt, .default_value = int64_t{-1}, .min = -1, .max = kMaxIterations,
       .help = "... and stay as they are after this one (0: never frozen; -1: the static stage's end in a field "
               "run, else never)",
       .apply = nullptr});
  add({.name = "lidar-weight", .type = T::kDouble, .default_value = 1.0, .min = 0, .max = 1e6,
       .help = "scale of the LiDAR losses' weights",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.lidar_weight = D(v); }});
  add({.name = "lidar-every", .type = T::kInt, .default_value = int64_t{2}, .min = 1, .max = 1'000'000,
       .help = "a LiDAR step every k-th iteration",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.lidar_every = static_cast<int>(I(v)); }});
  add({.name = "clip-overlap", .type = T::kInt, .default_value = int64_t{-1}, .min = -1, .max = 1'000'000,
       .help = "frames of each neighbour a clip also trains on (-1: a tenth of a clip)", .apply = nullptr});
  add({.name = "field-lr-scale", .type = T::kDouble, .default_value = 10.0, .min = 0, .max = 1000,
       .min_exclusive = true, .help = "the field's learning rates x S (1: S3Gaussian's)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.hyper.lr_scale = D(v); }});
  add({.name = "field-lr-decay-iterations", .type = T::kInt, .default_value = int64_t{30000}, .min = 1,
       .max = kMaxIterations, .help = "the field's rates decay over N fine iterations",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.hyper.lr_decay_steps = static_cast<int>(I(v)); }});
  add({.name = "field-motion-prior-scans", .type = T::kChoice, .default_value = std::string("last"),
       .choices = {"last", "all"}, .help = "which of a moving object's scans assign Gaussians to the prior",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.motion_prior.all_scans = S(v) == "all"; }});
  add({.name = "field-time-resolution", .type = T::kInt, .default_value = int64_t{25}, .min = 2, .max = 1000,
       .help = "cells of the field's space-time planes along time",
       .apply = [](const V& v, TrainRunOptions* o) {
         o->train.field.config.time_resolution = static_cast<int>(I(v));
       }});
  add({.name = "field-init", .type = T::kChoice, .default_value = std::string("spec"), .choices = {"spec", "zero-heads"},
       .help = "the field heads' init (zero-heads: the fine stage starts exactly from the static model)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.config.zero_init_heads = S(v) == "zero-heads"; }});
  add({.name = "field-lambda-dx", .type = T::kDouble, .default_value = 1e-3, .min = 0, .max = 100,
       .help = "weight of the Δx sparsity loss",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.hyper.lambda_dx = D(v); }});
  add({.name = "field-lambda-dsh", .type = T::kDouble, .default_value = 1e-3, .min = 0, .max = 100,
       .help = "weight of the ΔSH sparsity loss",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.hyper.lambda_dsh = D(v); }});
  add({.name = "field-l1-time-planes", .type = T::kDouble, .default_value = 1e-4, .min = 0, .max = 100,
       .help = "weight of the time planes' L1 towards 1",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.hyper.l1_time_planes = D(v); }});
  add({.name = "field-device", .type = T::kChoice, .default_value = std::string("auto"),
       .choices = {"auto", "cpu", "vulkan"}, .help = "where the field runs (auto: Vulkan on a GPU with backend vulkan)",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.device = *ParseFieldDevice(S(v)); }});
  add({.name = "field-optimizer", .type = T::kChoice, .default_value = std::string("auto"),
       .choices = {"auto", "device", "host"}, .help = "where a Vulkan field's regularisers and Adam run",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.optimizer = *ParseFieldOptimizerPlace(S(v)); }});
  add({.name = "field-modules", .type = T::kText, .default_value = std::string("all"), .check_text = CheckModules,
       .help = "field extended: its modules (encoder,vae,temporal,attention,gru,decoder; all; none)", .apply = nullptr});
  add({.name = "field-decoder-max-dlog-scale", .type = T::kDouble,
       .default_value = static_cast<double>(field::kDefaultDecoderMaxDlogScale), .min = 0, .max = 50,
       .help = "field extended: bound on the decoder's Δlog-scale (0: unbounded)", .apply = nullptr});
  add({.name = "field-ext-lr-scale", .type = T::kDouble, .default_value = 1.0, .min = 0, .max = 1000,
       .min_exclusive = true, .help = "field extended: the modules' network rate x S",
       .apply = [](const V& v, TrainRunOptions* o) { o->train.field.ext_hyper.lr_scale = D(v); }});
  add({.name = "field-ext-lr-decay-iterations", .type = T::kInt, .default_value = int64_t{30000}, .min = 1,
       .max = kMaxIterations, .help = "field extended: its decay over N fine iterations",
       .apply = [](const V& v, TrainRunOptions* o) {
         o->train.field.ext_hyper.lr_decay_steps = static_cast<int>(I(v));
       }});
  add({.name = "field-size", .type = T::kChoice, .default_value = std::string("spec"), .choices = {"spec", "small"},
       .help = "testing: small is a tiny field so that tests run in seconds", .apply = nullptr});
  return d;
}

constexpr const char* kExtendedOnly[] = {"field-modules", "field-decoder-max-dlog-scale", "field-ext-lr-scale",
                                         "field-ext-lr-decay-iterations"};

absl::Status ResolveField(const Settings& s, TrainRunOptions* o) {
  const std::string& field = s.GetText("field");
  TrainOptions& t = o->train;
  if (field == "auto") {
    // A static stage the user sized asks for the staged run; otherwise the run's length decides.
    t.field.mode = s.given("static-iterations") || t.iterations > t.field.static_iterations ? FieldMode::kS3Gaussian
                                                                                            : FieldMode::kStatic;
    o->field_chosen_by_default = t.field.mode == FieldMode::kS3Gaussian;
  } else {
    t.field.mode = field == "static" ? FieldMode::kStatic : FieldMode::kS3Gaussian;
  }
  if (field == "extended") {
    absl::StatusOr<field::ExtendedFieldConfig> ec = field::ExtendedFieldConfig::WithModules(s.GetText("field-modules"));
    if (!ec.ok()) return ec.status();
    if (s.given("field-decoder-max-dlog-scale") && !ec->decoder) {
      return absl::InvalidArgumentError("field-decoder-max-dlog-scale needs the decoder module (field-modules)");
    }
    ec->decoder_max_dlog_scale = static_cast<float>(s.GetDouble("field-decoder-max-dlog-scale"));
    t.field.extended = *ec;
  }
  if (t.field.mode == FieldMode::kS3Gaussian && t.field.static_iterations >= t.iterations) {
    return absl::InvalidArgumentError(absl::StrCat("static-iterations (", t.field.static_iterations,
                                                   ") must be below iterations (", t.iterations,
                                                   ") for a field run: the fine stage follows the static stage"));
  }
  if (s.GetText("field-size") == "small") {
    t.field.config.channels = 4;
    t.field.config.base_resolution = 8;
    t.field.config.multires = {1, 2};
    t.field.config.time_resolution = 6;
    t.field.config.width = 16;
  }
  if (s.given("field-time-resolution") || s.GetText("field-size") != "small") {
    t.field.config.time_resolution = static_cast<int>(s.GetInt("field-time-resolution"));
  }
  for (const std::string& name : FieldOnlySettings()) {
    // Given at its default it asks for nothing (`--field-motion-prior 0` on a static run).
    const SettingDef* def = s.Find(name);
    if (s.given(name) && t.field.mode == FieldMode::kStatic && s.Get(name) != def->default_value) {
      return absl::InvalidArgumentError(absl::StrCat(name, " needs a field (this run is static)"));
    }
  }
  for (const char* name : kExtendedOnly) {
    if (s.given(name) && !t.field.extended) {
      return absl::InvalidArgumentError(absl::StrCat(name, " needs field extended"));
    }
  }
  if (t.field.mode == FieldMode::kStatic) t.motion_prior.weight = 0;  // a preset's prior in a static run
  return absl::OkStatus();
}

absl::Status ResolvePoseSchedule(const Settings& s, TrainRunOptions* o) {
  TrainOptions& t = o->train;
  for (const std::string& name : PoseSettings()) {
    if (name != "pose-refinement" && s.given(name) && !t.pose_refinement) {
      return absl::InvalidArgumentError(absl::StrCat(name, " needs pose-refinement"));
    }
  }
  const int64_t until = s.GetInt("pose-refine-until");
  if (until >= 0) {
    t.hyper.pose_refine_until = until;
  } else if (t.field.mode != FieldMode::kStatic && t.field.static_iterations > t.hyper.pose_refine_from) {
    // A field run refines its poses on the static model and keeps them for the fine stage: kept
    // moving there, the corrections compete with the field for the same misalignment (KITTI, full
    // resolution: frozen +0.5..+1.2 dB held-out, refined throughout 0.5 dB behind them;
    // docs/benchmarks.md "Camera pose refinement").
    t.hyper.pose_refine_until = t.field.static_iterations;
  }
  return absl::OkStatus();
}

absl::Status ResolveLowResAndClips(const Settings& s, TrainRunOptions* o) {
  if (const int64_t n = s.GetInt("low-res-iterations"); n > 0) {
    o->train.low_res = LowResStage{s.GetDouble("low-res-scale"), n};
    if (absl::Status st = CheckLowResStage(o->train); !st.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("low-res-scale / low-res-iterations: ", st.message(), " (low-res-iterations 0: none)"));
    }
  }
  if (o->train.holdout_every == 1) {
    return absl::InvalidArgumentError("holdout-every must be 0 (none) or >= 2, not 1");
  }
  if (absl::Status st = PlanClips(1, o->clips.clip_frames).status(); !st.ok()) {
    return absl::InvalidArgumentError(absl::StrCat("clip-frames: ", st.message()));
  }
  if (s.given("clip-overlap") && s.GetInt("clip-overlap") < 0) {
    return absl::InvalidArgumentError("clip-overlap must be 0 .. clip-frames / 2, not -1 (-1 is its default: a tenth)");
  }
  if (const int64_t overlap = s.GetInt("clip-overlap"); overlap >= 0) {
    if (o->clips.clip_frames == 0) return absl::InvalidArgumentError("clip-overlap needs clip-frames > 0");
    if (absl::Status st = CheckClipOverlap(o->clips.clip_frames, static_cast<int>(overlap)); !st.ok()) {
      return absl::InvalidArgumentError(absl::StrCat("clip-overlap: ", st.message()));
    }
    o->clips.overlap_frames = static_cast<int>(overlap);
  }
  if (!s.GetBool("lidar-loss")) o->train.lidar_weight = 0;  // after lidar-weight's own apply
  if (s.given("lidar-weight") && !s.GetBool("lidar-loss")) {
    return absl::InvalidArgumentError("lidar-weight and lidar-loss false contradict each other");
  }
  return absl::OkStatus();
}

}  // namespace

const std::vector<SettingDef>& TrainSettingDefs() {
  static const std::vector<SettingDef>* defs = new std::vector<SettingDef>(MakeDefs());
  return *defs;
}

Settings DefaultTrainSettings() { return Settings(&TrainSettingDefs()); }

// Settings that only a field run uses: given in a static run they are a mistake worth saying.
const std::vector<std::string>& FieldOnlySettings() {
  static const std::vector<std::string> names = {
      "static-iterations",    "field-lr-scale",     "field-lr-decay-iterations", "field-time-resolution",
      "field-lambda-dx",      "field-lambda-dsh",   "field-l1-time-planes",      "field-motion-prior",
      "field-motion-prior-scans", "field-init"};
  return names;
}

const std::vector<std::string>& PoseSettings() {
  static const std::vector<std::string> names = {"pose-refinement", "pose-lr-scale", "pose-refine-from",
                                                 "pose-refine-until"};
  return names;
}

absl::StatusOr<TrainRunOptions> ResolveTrainOptions(const Settings& settings, int64_t segment_end) {
  TrainRunOptions o;
  for (const SettingDef& def : settings.defs()) {
    if (def.apply != nullptr) def.apply(settings.Get(def.name), &o);
  }
  // Order matters: the pose schedule's end follows the field.
  if (absl::Status s = ResolveField(settings, &o); !s.ok()) return s;
  if (absl::Status s = ResolvePoseSchedule(settings, &o); !s.ok()) return s;
  if (absl::Status s = ResolveLowResAndClips(settings, &o); !s.ok()) return s;
  if (segment_end > 0) {
    o.train.iterations = static_cast<int>(segment_end);
    if (segment_end <= o.train.field.static_iterations) {
      o.train.field.mode = FieldMode::kStatic;
      o.train.field.extended.reset();
      o.train.motion_prior.weight = 0;
    }
  }
  return o;
}

}  // namespace streetsim::train::config
