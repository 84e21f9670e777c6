// The scene's field as the trainer sees it (docs/training.md "Dynamic field"): no field (a static
// run), or S3Gaussian's (its extended form included: dynamic_stage.h) after a static warm-up.
// One interface, so that the loop never names a field's kind or an extended field's module; the
// field's checkpoint files, its record in checkpoint.json and train_meta.json, field.bin and the
// fine stage's timings are its own.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/train/checkpoint_run.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

class FieldPart {
 public:
  virtual ~FieldPart() = default;

  // Iteration `it` trains the field (a field run's fine stage).
  virtual bool Fine(int64_t it) const = 0;
  // The iteration counted from its stage's start (densification, opacity resets and the Gaussians'
  // rate decay restart with the fine stage).
  virtual int64_t StageIteration(int64_t it) const = 0;
  // The last iteration of the run's first stage (the run's own for a static run): the progress
  // line's time estimate is to there, the rate measured afresh after it.
  virtual int64_t FirstStageEnd() const = 0;

  // The parameters to render training view `view` with at iteration `it`, at SH degree `active`.
  // The fine stage's first iteration begins it (a new field over the Gaussians, which it reorders:
  // *began is then true).
  virtual absl::StatusOr<GaussianParamsView> Params(TrainState* st, int active, const View& view, int64_t it,
                                                    ThreadPool& pool, bool* began) = 0;
  // The means the last Params rendered when the field deformed them; null otherwise.
  virtual const std::vector<float>* DeformedMeans() const = 0;
  // After the parts' gradients: the field's own (and its regularisers', its Adam step); grads
  // become the canonical Gaussians'. Returns the loss terms it added.
  virtual absl::StatusOr<double> Backward(const TrainState& st, int active, int64_t stage_it, GaussianGrads* grads,
                                          ThreadPool& pool) = 0;
  // After densification changed the rows.
  virtual absl::Status RowsChanged(TrainState* st, ThreadPool& pool) = 0;

  // Checkpoints: the field's file for `iteration` before the Gaussians' (so that a crash between
  // the two never pairs a field with the wrong Gaussians), the older files after.
  virtual absl::Status SaveCheckpoint(const std::string& out_dir, int64_t iteration) = 0;
  virtual void RemoveOlderCheckpoints(const std::string& out_dir, int64_t iteration) const = 0;
  // Which field the checkpoint holds (checkpoint.json; a resume that changes the field is refused).
  virtual void Record(CheckpointRun* run) const = 0;
  // The run's end: field.bin (or its removal: a static run replaces an earlier field scene) and
  // the field's entries of train_meta.json.
  virtual absl::Status WriteOutputs(const std::string& out_dir, nlohmann::json* meta) = 0;
  // The trained field as evaluation renders it (null: none).
  virtual std::shared_ptr<const field::DeformationField> SceneField() const = 0;
  // The fine stage's timings line (empty: none).
  virtual std::string Summary() const = 0;
};

struct FieldPartOptions {
  FieldOptions field;  // the run's (seed, device and time range resolved)
  int64_t iterations = 0;
  bool deterministic = false;  // the field's backward on one thread
};

// The field of a run at `st`'s iteration in `out_dir`: a resumed fine stage from its checkpoint.
// FailedPrecondition when a static run would resume a field run's checkpoint.
absl::StatusOr<std::unique_ptr<FieldPart>> MakeFieldPart(const FieldPartOptions& options, const std::string& out_dir,
                                                         const TrainState& st);

}  // namespace streetsim::train
