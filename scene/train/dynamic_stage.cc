#include "scene/train/dynamic_stage.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <limits>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "scene/field/field_io.h"
#include "scene/field/field_regularizers.h"

namespace streetsim::train {

const char* FieldModeName(FieldMode mode) { return mode == FieldMode::kS3Gaussian ? "s3gaussian" : "static"; }

absl::StatusOr<FieldMode> ParseFieldMode(const std::string& text) {
  if (text == "static") return FieldMode::kStatic;
  if (text == "s3gaussian") return FieldMode::kS3Gaussian;
  return absl::InvalidArgumentError(absl::StrCat("--field must be static or s3gaussian, not '", text, "'"));
}

field::FieldAabb AabbOfMeans(const std::vector<float>& means) {
  field::FieldAabb box;
  const size_t n = means.size() / 3;
  if (n == 0) return box;  // the default [-1, 1]^3
  for (int a = 0; a < 3; ++a) {
    box.min[a] = std::numeric_limits<double>::infinity();
    box.max[a] = -std::numeric_limits<double>::infinity();
  }
  for (size_t i = 0; i < n; ++i) {
    for (int a = 0; a < 3; ++a) {
      const double v = means[i * 3 + a];
      if (!std::isfinite(v)) continue;
      box.min[a] = std::min(box.min[a], v);
      box.max[a] = std::max(box.max[a], v);
    }
  }
  for (int a = 0; a < 3; ++a) {
    if (!(box.max[a] >= box.min[a])) box.min[a] = -1, box.max[a] = 1;
    const double pad = std::max(0.01, 0.01 * (box.max[a] - box.min[a]));
    box.min[a] -= pad;
    box.max[a] += pad;
  }
  return box;
}

DynamicStage::DynamicStage(field::DeformationField f, field::FieldAdamState adam, const FieldOptions& options)
    : field_(std::move(f)), adam_(std::move(adam)), hyper_(options.hyper),
      ws_(std::make_unique<field::FieldWorkspace>()) {}

absl::StatusOr<std::unique_ptr<DynamicStage>> DynamicStage::Begin(TrainState* st, const FieldOptions& options,
                                                                   const field::FieldTimeRange& time_range) {
  absl::StatusOr<field::DeformationField> f =
      field::DeformationField::Create(options.config, AabbOfMeans(st->params.means), time_range, options.seed);
  if (!f.ok()) return f.status();
  field::FieldAdamState adam;
  adam.Init(f->layout().total);
  // The Gaussians' optimiser and densification statistics start afresh (training_setup per stage).
  for (GaussianStore* g : {&st->adam_m, &st->adam_v}) {
    for (std::vector<float>* a : {&g->means, &g->log_scales, &g->rotations, &g->opacity_logits, &g->sh}) {
      std::fill(a->begin(), a->end(), 0.0f);
    }
  }
  st->adam_step = 0;
  std::fill(st->grad_accum.begin(), st->grad_accum.end(), 0.0f);
  std::fill(st->denom.begin(), st->denom.end(), 0.0f);
  std::fill(st->max_radii.begin(), st->max_radii.end(), 0.0f);
  return std::unique_ptr<DynamicStage>(new DynamicStage(std::move(*f), std::move(adam), options));
}

absl::StatusOr<std::unique_ptr<DynamicStage>> DynamicStage::Resume(const std::string& path,
                                                                    const FieldOptions& options,
                                                                    int64_t fine_iterations) {
  absl::StatusOr<field::FieldCheckpoint> ck = field::LoadFieldCheckpoint(path);
  if (!ck.ok()) return ck.status();
  // Every fine iteration steps the field's Adam once.
  if (ck->adam.step != fine_iterations) {
    return absl::FailedPreconditionError(absl::StrCat(path, ": the field has ", ck->adam.step,
                                                      " fine iterations, the Gaussian checkpoint ", fine_iterations,
                                                      " (was --static-iterations changed?)"));
  }
  return std::unique_ptr<DynamicStage>(new DynamicStage(std::move(ck->field), std::move(ck->adam), options));
}

absl::Status DynamicStage::SaveCheckpoint(const std::string& path) const {
  return field::SaveFieldCheckpoint(field_, adam_, path);
}

absl::StatusOr<GaussianParamsView> DynamicStage::Deform(const TrainState& st, int active_degree, int64_t time_us,
                                                        ThreadPool& pool) {
  field::CanonicalView c{st.size(), st.params.means.data(), st.params.sh.data()};
  if (absl::Status s = field::DeformScene(field_, field_.TimeCoordinate(time_us), c, pool, *ws_, &deformed_); !s.ok()) {
    return s;
  }
  // Colour direction: the engine takes it from the means it renders, i.e. the deformed ones
  // (S3Gaussian uses the canonical xyz, spec quirk 4).
  return field::DeformedParamsView(ParamsView(st, active_degree), deformed_);
}

absl::StatusOr<double> DynamicStage::Backward(const TrainState& st, int active_degree, int64_t fine_iteration,
                                              GaussianGrads* grads, ThreadPool& pool) {
  field::CanonicalView c{st.size(), st.params.means.data(), st.params.sh.data()};
  if (deformed_.dx.size() != c.n * 3) return absl::InternalError("DynamicStage::Backward without a matching Deform");
  if (d_field_.size() == field_.layout().total) {
    std::fill(d_field_.begin(), d_field_.end(), 0.0f);
  } else {
    d_field_.assign(field_.layout().total, 0.0f);
  }
  absl::StatusOr<field::DeformLosses> dl =
      field::DeformBackward(field_, c, deformed_, active_degree, hyper_, pool, *ws_, grads, &d_field_);
  if (!dl.ok()) return dl.status();
  field::RegularizerWeights w;
  w.plane_tv = hyper_.plane_tv_weight;
  w.time_smoothness = hyper_.time_smoothness_weight;
  w.l1_time_planes = hyper_.l1_time_planes;
  const field::RegularizerLosses reg =
      field::PlaneRegularizers<float>(field_.layout(), field_.params().data(), w, d_field_.data(), pool);
  field::FieldAdamStep(field_.layout(), field_.mutable_params().data(), d_field_.data(), &adam_,
                       field::FieldLearningRates(hyper_, fine_iteration, st.extent), pool);
  return dl->weighted + reg.weighted;
}

std::string FieldCheckpointPath(const std::string& out_dir, int64_t iteration) {
  return (std::filesystem::path(out_dir) / absl::StrCat("checkpoint_field_", iteration, ".bin")).string();
}

void RemoveFieldCheckpoints(const std::string& out_dir, int64_t keep_iteration) {
  std::error_code ec;
  const std::string keep = keep_iteration >= 0 ? FieldCheckpointPath(out_dir, keep_iteration) : "";
  std::vector<std::filesystem::path> doomed;
  for (const auto& e : std::filesystem::directory_iterator(out_dir, ec)) {
    const std::string name = e.path().filename().string();
    if (name.rfind("checkpoint_field_", 0) == 0 && e.path().string() != keep) doomed.push_back(e.path());
  }
  for (const auto& p : doomed) std::filesystem::remove(p, ec);
}

absl::StatusOr<GaussianStore> DeformedStore(const field::DeformationField& f, const GaussianStore& canonical,
                                            int64_t time_us, ThreadPool& pool) {
  if (canonical.sh_degree != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
  }
  field::FieldWorkspace ws;
  field::DeformedScene d;
  field::CanonicalView c{canonical.size(), canonical.means.data(), canonical.sh.data()};
  if (absl::Status s = field::DeformScene(f, f.TimeCoordinate(time_us), c, pool, ws, &d); !s.ok()) return s;
  GaussianStore out = canonical;
  out.means = std::move(d.means);
  out.sh = std::move(d.sh);
  return out;
}

absl::StatusOr<SceneForView> MakeSceneForView(Engine& engine, const GaussianStore& canonical,
                                              std::shared_ptr<const field::DeformationField> f) {
  if (!f) {
    absl::StatusOr<std::unique_ptr<DeviceScene>> dev = engine.Upload(canonical);
    if (!dev.ok()) return dev.status();
    std::shared_ptr<DeviceScene> scene = std::move(*dev);
    return SceneForView([scene](const View&) -> absl::StatusOr<const DeviceScene*> { return scene.get(); });
  }
  if (canonical.sh_degree != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
  }
  auto pool = std::make_shared<ThreadPool>(0);
  auto scene = std::make_shared<std::unique_ptr<DeviceScene>>();
  auto canon = std::make_shared<GaussianStore>(canonical);
  Engine* e = &engine;
  return SceneForView([=](const View& v) -> absl::StatusOr<const DeviceScene*> {
    absl::StatusOr<GaussianStore> d = DeformedStore(*f, *canon, v.time_us, *pool);
    if (!d.ok()) return d.status();
    if (absl::Status s = e->UpdateScene(*d, scene.get()); !s.ok()) return s;
    return scene->get();
  });
}

std::function<absl::StatusOr<GaussianStore>(int64_t time_us)> MakeStoreAtTime(
    std::shared_ptr<const field::DeformationField> f, const GaussianStore& canonical) {
  if (!f) return {};
  auto pool = std::make_shared<ThreadPool>(0);
  const GaussianStore* canon = &canonical;
  return [f, pool, canon](int64_t time_us) { return DeformedStore(*f, *canon, time_us, *pool); };
}

absl::StatusOr<std::shared_ptr<const field::DeformationField>> LoadSceneField(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / field::kFieldFileName).string();
  if (!std::filesystem::exists(path)) return std::shared_ptr<const field::DeformationField>();
  absl::StatusOr<field::DeformationField> f = field::LoadField(path);
  if (!f.ok()) return f.status();
  return std::make_shared<const field::DeformationField>(std::move(*f));
}

}  // namespace streetsim::train
