// A trained scene as `streetsim serve` serves it (scene/field/static_skip.h ServingField; with an
// extension, extended_serving.h ExtServingField): the static skip's Gaussians baked at their
// time-mean deformation, the others evaluated per timestamp. `streetsim eval --served` renders
// through this, so the quality cost of a pair of skip thresholds is measured against the log
// rather than guessed (docs/field.md "Serving").
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <variant>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/extended/extended_field.h"
#include "scene/field/extended/extended_serving.h"
#include "scene/field/serving_form.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/train/dynamic_stage.h"
#include "scene/eval/lidar_eval.h"

namespace streetsim::train {

// A trained field as served: the S3Gaussian field, or an extended one (which holds its base).
using ExactField = std::variant<field::DeformationField, field::ExtendedField>;

// Where a served field is evaluated (e.g. vulkan_serving.h's forwards); null: the cpu.
struct ServedFieldDevice {
  const field::ServingField::Device* field = nullptr;
  const field::ExtServingField::Device* extended = nullptr;
};

// The served scene of `canonical` under `field`, after the static analysis with `options` (run on
// `pool`), evaluated on `device`. By value, so that a caller that loaded the field for this (the
// server) moves it in rather than holding a second copy of a field of hundreds of MB.
absl::StatusOr<std::unique_ptr<field::ServedScene>> MakeExactServedScene(ExactField field, GaussianStore canonical,
                                                                         const field::StaticSkipOptions& options,
                                                                         ThreadPool& pool,
                                                                         const ServedFieldDevice& device = {});

// The same for a shared field (an extended field when LoadSceneField attached one), copied; on the
// cpu, the analysis on `pool` (null: every core). `field` must not be null.
absl::StatusOr<std::unique_ptr<field::ServedScene>> MakeExactServedScene(
    std::shared_ptr<const field::DeformationField> field, const GaussianStore& canonical,
    const field::StaticSkipOptions& options, ThreadPool* pool = nullptr);
absl::StatusOr<std::shared_ptr<field::ServedScene>> MakeServedScene(
    std::shared_ptr<const field::DeformationField> field, const GaussianStore& canonical,
    const field::StaticSkipOptions& options, ThreadPool* pool = nullptr);

// The trained scene in `dir` as `streetsim serve` serves it by default: its serving form
// (scene/field/serving_form.h), read from DIR/field.serving when that was built from DIR's
// scene.ply, field.bin and field_ext.bin with these options, else built from make_exact()'s exact
// served scene and written there (a stale, damaged or unwritable cache: a warning, never served).
// A form whose measured error misses form.max_position_error_m is not served: the exact scene is,
// with a warning (a field with more motion in time than the spline follows).
absl::StatusOr<std::unique_ptr<field::ServedScene>> LoadServedScene(
    const std::string& dir, const std::function<absl::StatusOr<std::unique_ptr<field::ServedScene>>()>& make_exact,
    const field::ServingFormOptions& form, const field::StaticSkipOptions& skip, ThreadPool* pool = nullptr);

// Views and LiDAR sweeps rendered from `served` at their times (one served scene, evaluated once
// per distinct timestamp; not thread-safe, as eval is sequential). Valid while the engine is.
absl::StatusOr<SceneForView> MakeServedSceneForView(Engine& engine, std::shared_ptr<field::ServedScene> served);
StoreAtTime MakeServedStoreAtTime(std::shared_ptr<field::ServedScene> served);

}  // namespace streetsim::train
