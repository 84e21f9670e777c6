#include "server/training_config.h"

#include <charconv>
#include <cmath>
#include <regex>

#include "absl/strings/str_cat.h"
#include "render/engine.h"
#include "scene/field/extended/extended_config.h"
#include "scene/train/clips.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/motion_prior.h"
#include "scene/train/resolution_schedule.h"
#include "server/echo.h"

namespace streetsim::server {
namespace {

constexpr int kMaxIterations = 10'000'000;  // `streetsim train --iterations`' own bound

absl::Status Bad(const std::string& message) {
  return absl::InvalidArgumentError(absl::StrCat("config.", message));
}

// The field the trainer will pick: the config's, else its default rule (docs/training.md
// "Default field": S3Gaussian's when the run is longer than the static warm-up or one is given);
// "" for a continuation that does not say (the trainer keeps the scene's own: the job runner
// checks that one, CheckContinuation).
std::string EffectiveField(const v1::TrainingConfig& c) {
  if (!c.field().empty()) return c.field();
  if (!c.continue_from_scene().empty()) return "";
  if (c.has_static_iterations()) return "s3gaussian";
  return c.max_iterations() > train::FieldOptions{}.static_iterations ? "s3gaussian" : "static";
}

// The shortest text that parses back to exactly v (absl::StrCat keeps 6 digits: the trainer would
// get another scale than the job asked for).
std::string Number(double v) {
  char buf[32];
  const std::to_chars_result r = std::to_chars(buf, buf + sizeof(buf), v);
  return std::string(buf, r.ptr);
}

}  // namespace

bool IsSceneName(const std::string& name) {
  static const std::regex kName("[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}");
  return std::regex_match(name, kName);
}

absl::Status ValidateTrainingConfig(const v1::TrainingConfig& c) {
  if (c.max_iterations() < 0 || c.max_iterations() > kMaxIterations) {
    return Bad(absl::StrCat("max_iterations must be in 0..", kMaxIterations));
  }
  const bool asks_training_options =
      !c.field().empty() || !c.field_modules().empty() || c.has_static_iterations() || c.resolution_scale() != 0 ||
      c.low_res_scale() != 0 || c.low_res_iterations() != 0 || c.has_holdout_every() || c.clip_frames() != 0 ||
      c.has_clip_overlap() || c.field_lr_scale() != 0 || c.field_lr_decay_iterations() != 0 || !c.backend().empty() ||
      !c.continue_from_scene().empty() || c.pose_refinement() || c.pose_lr_scale() != 0 ||
      c.position_lr_decay_iterations() != 0 || c.field_ext_lr_scale() != 0 || c.field_ext_lr_decay_iterations() != 0 ||
      c.has_field_motion_prior() || !c.field_motion_prior_scans().empty() || c.has_densify_until();
  if (c.max_iterations() == 0) {
    if (asks_training_options) return Bad("training options need max_iterations > 0 (0 is init only)");
    return absl::OkStatus();
  }
  if (!c.field().empty() && c.field() != "static" && c.field() != "s3gaussian" && c.field() != "extended") {
    return Bad(absl::StrCat("field must be static, s3gaussian, extended or empty, not ", Echo(c.field())));
  }
  const std::string field = EffectiveField(c);
  if (!c.field_modules().empty()) {
    if (field != "extended") return Bad("field_modules needs field \"extended\"");
    if (absl::Status s = field::ExtendedFieldConfig::WithModules(c.field_modules()).status(); !s.ok()) {
      return Bad(absl::StrCat("field_modules: ", s.message()));
    }
  }
  if (c.has_static_iterations()) {
    if (field == "static") return Bad("static_iterations needs a field (field \"static\" has no fine stage)");
    if (c.static_iterations() < 0 || c.static_iterations() >= c.max_iterations()) {
      return Bad(absl::StrCat("static_iterations must be in 0..", c.max_iterations() - 1, " (below max_iterations)"));
    }
  } else if (!field.empty() && field != "static" && train::FieldOptions{}.static_iterations >= c.max_iterations()) {
    return Bad(absl::StrCat("field \"", field, "\": the static warm-up (", train::FieldOptions{}.static_iterations,
                            " iterations by default) must be shorter than max_iterations; set static_iterations"));
  }
  if (field == "static") {
    if (c.field_lr_scale() != 0 || c.field_lr_decay_iterations() != 0) {
      return Bad("field_lr_scale / field_lr_decay_iterations need a field (this run is static)");
    }
    if (c.has_field_motion_prior()) return Bad("field_motion_prior needs a field (this run is static)");
    if (!c.field_motion_prior_scans().empty()) {
      return Bad("field_motion_prior_scans needs a field (this run is static)");
    }
  }
  if (!c.field_motion_prior_scans().empty() && !train::ParseMotionPriorScans(c.field_motion_prior_scans())) {
    return Bad(
        absl::StrCat("field_motion_prior_scans must be last, all or empty, not ", Echo(c.field_motion_prior_scans())));
  }
  if (c.has_field_motion_prior() &&
      !(c.field_motion_prior() >= 0 && c.field_motion_prior() <= train::kMaxMotionPriorWeight)) {
    return Bad("field_motion_prior must be in [0, 10000] (0: off)");
  }
  if (!(std::isfinite(c.field_lr_scale()) && c.field_lr_scale() >= 0 && c.field_lr_scale() <= 1000)) {
    return Bad("field_lr_scale must be in (0, 1000] (0: the default)");
  }
  if (c.field_lr_decay_iterations() < 0 || c.field_lr_decay_iterations() > kMaxIterations) {
    return Bad(absl::StrCat("field_lr_decay_iterations must be in 1..", kMaxIterations, " (0: the default)"));
  }
  if ((c.field_ext_lr_scale() != 0 || c.field_ext_lr_decay_iterations() != 0) && field != "extended") {
    return Bad("field_ext_lr_scale / field_ext_lr_decay_iterations need field \"extended\"");
  }
  if (!(std::isfinite(c.field_ext_lr_scale()) && c.field_ext_lr_scale() >= 0 && c.field_ext_lr_scale() <= 1000)) {
    return Bad("field_ext_lr_scale must be in (0, 1000] (0: the default)");
  }
  if (c.field_ext_lr_decay_iterations() < 0 || c.field_ext_lr_decay_iterations() > kMaxIterations) {
    return Bad(absl::StrCat("field_ext_lr_decay_iterations must be in 1..", kMaxIterations, " (0: the default)"));
  }
  if (c.position_lr_decay_iterations() < 0 || c.position_lr_decay_iterations() > kMaxIterations) {
    return Bad(absl::StrCat("position_lr_decay_iterations must be in 1..", kMaxIterations, " (0: the default)"));
  }
  if (c.has_densify_until() && (c.densify_until() < 0 || c.densify_until() > kMaxIterations)) {
    return Bad(absl::StrCat("densify_until must be in 0..", kMaxIterations));
  }
  if (!(std::isfinite(c.resolution_scale()) && c.resolution_scale() >= 0 && c.resolution_scale() <= 1)) {
    return Bad("resolution_scale must be in (0, 1] (0: 1)");
  }
  if ((c.low_res_scale() != 0) != (c.low_res_iterations() != 0)) {
    return Bad("low_res_scale and low_res_iterations go together");
  }
  if (c.low_res_iterations() != 0) {
    if (!std::isfinite(c.low_res_scale())) return Bad("low_res_scale must be a finite number");
    train::TrainOptions opt;
    opt.iterations = c.max_iterations();
    opt.resolution_scale = c.resolution_scale() == 0 ? 1.0 : c.resolution_scale();
    opt.low_res = train::LowResStage{c.low_res_scale(), c.low_res_iterations()};
    if (absl::Status s = train::CheckLowResStage(opt); !s.ok()) {
      return Bad(absl::StrCat("low_res_scale / low_res_iterations: ", s.message()));
    }
  }
  if (c.has_holdout_every() && (c.holdout_every() < 0 || c.holdout_every() == 1)) {
    return Bad("holdout_every must be 0 (none) or >= 2");
  }
  if (absl::Status s = train::PlanClips(1, c.clip_frames()).status(); !s.ok()) {
    return Bad(absl::StrCat("clip_frames: ", s.message()));
  }
  if (c.has_clip_overlap()) {
    if (c.clip_frames() == 0) return Bad("clip_overlap needs clip_frames");
    if (absl::Status s = train::CheckClipOverlap(c.clip_frames(), c.clip_overlap()); !s.ok()) {
      return Bad(absl::StrCat("clip_overlap: ", s.message()));
    }
  }
  if (!(std::isfinite(c.pose_lr_scale()) && c.pose_lr_scale() >= 0 && c.pose_lr_scale() <= 1000)) {
    return Bad("pose_lr_scale must be in (0, 1000] (0: the default)");
  }
  if (c.pose_lr_scale() != 0 && !c.pose_refinement()) return Bad("pose_lr_scale needs pose_refinement");
  if (!c.continue_from_scene().empty() && !IsSceneName(c.continue_from_scene())) {
    return Bad("continue_from_scene: 1-64 of [A-Za-z0-9_.-], not starting with '.'");
  }
  if (!c.backend().empty()) {
    if (absl::Status s = ParseBackend(c.backend()).status(); !s.ok()) {
      return Bad(absl::StrCat("backend: ", s.message()));
    }
  }
  return absl::OkStatus();
}

std::vector<std::string> TrainFlags(const v1::TrainingConfig& c) {
  std::vector<std::string> f;
  auto add = [&](const char* flag, const std::string& value) { f.insert(f.end(), {flag, value}); };
  if (c.seed() != 0) add("--seed", std::to_string(c.seed()));
  if (!c.field().empty()) add("--field", c.field());
  if (!c.field_modules().empty()) add("--field-modules", c.field_modules());
  if (c.has_static_iterations()) add("--static-iterations", std::to_string(c.static_iterations()));
  if (c.resolution_scale() != 0) add("--resolution-scale", Number(c.resolution_scale()));
  if (c.low_res_iterations() != 0) {
    add("--low-res-scale", Number(c.low_res_scale()));
    add("--low-res-iterations", std::to_string(c.low_res_iterations()));
  }
  if (c.has_holdout_every()) add("--holdout-every", std::to_string(c.holdout_every()));
  if (c.clip_frames() != 0) add("--clip-frames", std::to_string(c.clip_frames()));
  if (c.has_clip_overlap()) add("--clip-overlap", std::to_string(c.clip_overlap()));
  if (c.field_lr_scale() != 0) add("--field-lr-scale", Number(c.field_lr_scale()));
  if (c.field_lr_decay_iterations() != 0) add("--field-lr-decay-iterations", std::to_string(c.field_lr_decay_iterations()));
  if (c.position_lr_decay_iterations() != 0) {
    add("--position-lr-decay-iterations", std::to_string(c.position_lr_decay_iterations()));
  }
  if (c.has_densify_until()) add("--densify-until", std::to_string(c.densify_until()));
  if (c.field_ext_lr_scale() != 0) add("--field-ext-lr-scale", Number(c.field_ext_lr_scale()));
  if (c.field_ext_lr_decay_iterations() != 0) {
    add("--field-ext-lr-decay-iterations", std::to_string(c.field_ext_lr_decay_iterations()));
  }
  if (c.has_field_motion_prior()) add("--field-motion-prior", Number(c.field_motion_prior()));
  if (!c.field_motion_prior_scans().empty()) add("--field-motion-prior-scans", c.field_motion_prior_scans());
  if (!c.backend().empty()) add("--backend", c.backend());
  if (c.pose_refinement()) f.push_back("--pose-refinement");
  if (c.pose_lr_scale() != 0) add("--pose-lr-scale", Number(c.pose_lr_scale()));
  return f;
}

}  // namespace streetsim::server
