#include "scene/train/parts/field_part.h"

#include <filesystem>

#include <nlohmann/json.hpp>

#include "render/common/log.h"
#include "scene/field/field_io.h"

namespace streetsim::train {
namespace {

namespace fs = std::filesystem;

class NoField : public FieldPart {
 public:
  explicit NoField(int64_t iterations) : iterations_(iterations) {}
  bool Fine(int64_t) const override { return false; }
  int64_t StageIteration(int64_t it) const override { return it; }
  int64_t FirstStageEnd() const override { return iterations_; }
  absl::StatusOr<GaussianParamsView> Params(TrainState* st, int active, const View&, int64_t, ThreadPool&,
                                            bool* began) override {
    *began = false;
    return ParamsView(*st, active);
  }
  const std::vector<float>* DeformedMeans() const override { return nullptr; }
  absl::StatusOr<double> Backward(const TrainState&, int, int64_t, GaussianGrads*, ThreadPool&) override {
    return 0.0;
  }
  absl::Status RowsChanged(TrainState*, ThreadPool&) override { return absl::OkStatus(); }
  absl::Status SaveCheckpoint(const std::string&, int64_t) override { return absl::OkStatus(); }
  void RemoveOlderCheckpoints(const std::string& out_dir, int64_t) const override {
    RemoveFieldCheckpoints(out_dir, -1);
  }
  void Record(CheckpointRun* run) const override { run->field = "static"; }
  absl::Status WriteOutputs(const std::string& out_dir, nlohmann::json* meta) override {
    (*meta)["field"] = "static";
    std::error_code ec;
    fs::remove(fs::path(out_dir) / field::kFieldFileName, ec);  // a static run replaces an earlier field scene
    return absl::OkStatus();
  }
  std::shared_ptr<const field::DeformationField> SceneField() const override { return nullptr; }
  std::string Summary() const override { return {}; }

 private:
  int64_t iterations_;
};

// S3Gaussian's stages: static for static_iterations, then the field.
class StagedField : public FieldPart {
 public:
  StagedField(const FieldPartOptions& o, std::unique_ptr<DynamicStage> resumed)
      : opt_(o.field), static_its_(o.field.static_iterations), stage_(std::move(resumed)) {
    // The field's backward sums MLP gradients per thread in scheduling order: one thread when the
    // run should be reproducible (docs/training.md "Reproducibility").
    if (o.deterministic) serial_pool_ = std::make_unique<ThreadPool>(1);
  }

  bool Fine(int64_t it) const override { return it > static_its_; }
  int64_t StageIteration(int64_t it) const override { return Fine(it) ? it - static_its_ : it; }
  int64_t FirstStageEnd() const override { return static_its_; }

  absl::StatusOr<GaussianParamsView> Params(TrainState* st, int active, const View& view, int64_t it,
                                            ThreadPool& pool, bool* began) override {
    *began = false;
    if (!Fine(it)) return ParamsView(*st, active);
    if (!stage_) {
      absl::StatusOr<std::unique_ptr<DynamicStage>> b = DynamicStage::Begin(st, opt_, opt_.time_range);
      if (!b.ok()) return b.status();
      stage_ = std::move(*b);
      if (absl::Status s = stage_->OrderGaussians(st, pool); !s.ok()) return s;
      LOG(INFO) << "iteration " << it << ": fine stage, field of " << stage_->field().layout().total << " parameters";
      *began = true;
    }
    return stage_->Deform(*st, active, view.time_us, pool);
  }
  const std::vector<float>* DeformedMeans() const override { return stage_ ? &stage_->deformed_means() : nullptr; }
  absl::StatusOr<double> Backward(const TrainState& st, int active, int64_t stage_it, GaussianGrads* grads,
                                  ThreadPool& pool) override {
    if (!stage_) return 0.0;
    return stage_->Backward(st, active, stage_it, grads, serial_pool_ ? *serial_pool_ : pool);
  }
  absl::Status RowsChanged(TrainState* st, ThreadPool& pool) override {
    return stage_ ? stage_->OrderGaussians(st, pool) : absl::OkStatus();
  }

  absl::Status SaveCheckpoint(const std::string& out_dir, int64_t iteration) override {
    return stage_ ? stage_->SaveCheckpoint(FieldCheckpointPath(out_dir, iteration)) : absl::OkStatus();
  }
  void RemoveOlderCheckpoints(const std::string& out_dir, int64_t iteration) const override {
    RemoveFieldCheckpoints(out_dir, stage_ ? iteration : -1);
  }
  void Record(CheckpointRun* run) const override {
    run->field = opt_.extended ? "extended" : "s3gaussian";
    if (stage_ && stage_->extended()) run->field_extension_from = stage_->extension_from_fine_iteration();
  }
  absl::Status WriteOutputs(const std::string& out_dir, nlohmann::json* meta) override;
  std::shared_ptr<const field::DeformationField> SceneField() const override {
    return stage_ ? stage_->SceneField() : nullptr;
  }
  std::string Summary() const override {
    return stage_ && stage_->timings().iterations > 0 ? stage_->timings().Summary() : std::string();
  }

 private:
  FieldOptions opt_;
  int64_t static_its_;
  std::unique_ptr<DynamicStage> stage_;
  std::unique_ptr<ThreadPool> serial_pool_;
};

absl::Status StagedField::WriteOutputs(const std::string& out_dir, nlohmann::json* meta) {
  nlohmann::json& m = *meta;
  const fs::path field_path = fs::path(out_dir) / field::kFieldFileName;
  if (!stage_) {  // a run that ended before its fine stage wrote no field
    m["field"] = "static";
    std::error_code ec;
    fs::remove(field_path, ec);
    return absl::OkStatus();
  }
  m["field"] = opt_.extended ? "extended" : "s3gaussian";
  if (opt_.extended) {
    m["field_modules"] = opt_.extended->ModulesString();
    m["field_ext_lr_scale"] = opt_.ext_hyper.lr_scale;  // the extension's network rate
    m["field_ext_lr_decay_iterations"] = opt_.ext_hyper.lr_decay_steps;
  }
  if (stage_->extended() && stage_->extension_from_fine_iteration() > 0) {
    m["field_extension_from"] = stage_->extension_from_fine_iteration();  // grown on a resume
  }
  if (stage_->extended() && stage_->extended()->config().decoder) {
    // The trained field's own (a resumed stage keeps its checkpoint's): 0 = unbounded.
    m["field_decoder_max_dlog_scale"] = stage_->extended()->config().decoder_max_dlog_scale;
  }
  if (absl::Status s = stage_->SyncHost(); !s.ok()) return s;  // the field's optimiser may be on the device
  m["static_iterations"] = static_its_;
  m["field_lambda_dx"] = opt_.hyper.lambda_dx;  // the Δ sparsity weights trained with
  m["field_lambda_dsh"] = opt_.hyper.lambda_dsh;
  m["field_l1_time_planes"] = opt_.hyper.l1_time_planes;
  m["field_lr_scale"] = opt_.hyper.lr_scale;  // the field's learning-rate schedule
  m["field_lr_decay_iterations"] = opt_.hyper.lr_decay_steps;
  m["field_time_resolution"] = stage_->field().config().time_resolution;  // cells along time
  m["time_range_us"] = {stage_->field().time_range().start_us, stage_->field().time_range().end_us};
  return field::SaveField(stage_->field(), field_path.string());
}

}  // namespace

absl::StatusOr<std::unique_ptr<FieldPart>> MakeFieldPart(const FieldPartOptions& o, const std::string& out_dir,
                                                         const TrainState& st) {
  if (o.field.mode != FieldMode::kS3Gaussian) {
    if (st.iteration > 0 && fs::exists(FieldCheckpointPath(out_dir, st.iteration))) {
      return absl::FailedPreconditionError("the checkpoint is from a --field s3gaussian run; resume it with that");
    }
    return std::unique_ptr<FieldPart>(new NoField(o.iterations));
  }
  std::unique_ptr<DynamicStage> resumed;
  const int64_t static_its = o.field.static_iterations;
  if (st.iteration > static_its) {
    absl::StatusOr<std::unique_ptr<DynamicStage>> r =
        DynamicStage::Resume(FieldCheckpointPath(out_dir, st.iteration), o.field, st.iteration - static_its);
    if (!r.ok()) return r.status();
    resumed = std::move(*r);
  }
  return std::unique_ptr<FieldPart>(new StagedField(o, std::move(resumed)));
}

}  // namespace streetsim::train
