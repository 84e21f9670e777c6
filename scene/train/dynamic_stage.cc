#include "scene/train/dynamic_stage.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <limits>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "render/common/log.h"
#include "render/vulkan/vulkan_engine.h"
#include "scene/field/field_io.h"
#include "scene/field/field_regularizers.h"
#include "scene/field/spatial_order.h"
#include "render/vulkan/field/vulkan_deformed_scene.h"
#include "scene/train/gradient_guard.h"

namespace streetsim::train {

namespace {

using Clock = std::chrono::steady_clock;
double MsSince(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

field::RegularizerWeights PlaneRegularizerWeights(const field::FieldHyper& hyper) {
  field::RegularizerWeights w;
  w.plane_tv = hyper.plane_tv_weight;
  w.time_smoothness = hyper.time_smoothness_weight;
  w.l1_time_planes = hyper.l1_time_planes;
  return w;
}

// The base field's plane regularizers (their gradient added into d_field) and its Adam step on the
// host, as both the S3Gaussian and the extended stage take them; returns the regularizers'
// weighted loss.
absl::StatusOr<double> RegularizeAndStepBaseField(const field::FieldHyper& hyper, int64_t fine_iteration,
                                                  double extent, ThreadPool& pool, field::DeformationField& base,
                                                  std::vector<float>& d_field, field::FieldAdamState* adam,
                                                  FineStageTimings* timings) {
  auto t0 = Clock::now();
  if (absl::Status s = CheckFiniteNetworkGradient(fine_iteration, "deformation field", d_field.data(),
                                                  d_field.size(), pool);
      !s.ok()) {
    return s;
  }
  timings->gradient_check_ms += MsSince(t0);
  const field::RegularizerWeights w = PlaneRegularizerWeights(hyper);
  t0 = Clock::now();
  const field::RegularizerLosses reg =
      field::PlaneRegularizers<float>(base.layout(), base.params().data(), w, d_field.data(), pool);
  timings->regularizers_ms += MsSince(t0);
  t0 = Clock::now();
  field::FieldAdamStep(base.layout(), base.mutable_params().data(), d_field.data(), adam,
                       field::FieldLearningRates(hyper, fine_iteration, extent), pool);
  timings->adam_ms += MsSince(t0);
  return reg.weighted;
}

// The extension of this clip's fine stage from the previous clip's: its parameters, this run's
// config (Δ follows this clip's time axis). Modules and sizes must match.
absl::StatusOr<field::ExtendedField> ExtendedFromPrior(field::DeformationField base,
                                                       const field::ExtendedFieldConfig& ec,
                                                       const field::ExtendedField& prior) {
  const field::ExtendedFieldConfig& pc = prior.config();
  const bool same = pc.ModulesString() == ec.ModulesString() && pc.heads == ec.heads &&
                    pc.vae_latent == ec.vae_latent && pc.vae_dilation == ec.vae_dilation &&
                    pc.gru_hidden == ec.gru_hidden && pc.window_k == ec.window_k &&
                    pc.fourier_frequencies == ec.fourier_frequencies && pc.encoder_layers == ec.encoder_layers &&
                    pc.activation == ec.activation;
  if (!same) {
    return absl::FailedPreconditionError(absl::StrCat("the previous clip's extension (--field-modules ",
                                                      pc.ModulesString(), ") does not match this run's (",
                                                      ec.ModulesString(), ", or its sizes differ)"));
  }
  return field::ExtendedField::FromParams(std::move(base), ec, prior.params());
}

}  // namespace

const char* FieldModeName(FieldMode mode) { return mode == FieldMode::kS3Gaussian ? "s3gaussian" : "static"; }

absl::StatusOr<FieldDevice> ParseFieldDevice(const std::string& text) {
  if (text == "auto") return FieldDevice::kAuto;
  if (text == "cpu") return FieldDevice::kCpu;
  if (text == "vulkan") return FieldDevice::kVulkan;
  return absl::InvalidArgumentError(absl::StrCat("--field-device must be auto, cpu or vulkan, not '", text, "'"));
}

absl::StatusOr<FieldOptimizerPlace> ParseFieldOptimizerPlace(const std::string& text) {
  if (text == "auto") return FieldOptimizerPlace::kAuto;
  if (text == "device") return FieldOptimizerPlace::kDevice;
  if (text == "host") return FieldOptimizerPlace::kHost;
  return absl::InvalidArgumentError(
      absl::StrCat("--field-optimizer must be auto, device or host, not '", text, "'"));
}

FieldDevice ResolveFieldDevice(FieldDevice device, Backend backend) {
  if (device != FieldDevice::kAuto) return device;
  return backend == Backend::kVulkan && HasVulkanGpu() ? FieldDevice::kVulkan : FieldDevice::kCpu;
}

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
      ws_(std::make_unique<field::FieldWorkspace>()),
      use_vulkan_(options.device == FieldDevice::kVulkan),
      optimizer_place_(options.optimizer),
      ext_hyper_(options.ext_hyper),
      ext_noise_seed_(options.seed) {}

absl::StatusOr<std::unique_ptr<DynamicStage>> DynamicStage::Begin(TrainState* st, const FieldOptions& options,
                                                                   const field::FieldTimeRange& time_range) {
  absl::StatusOr<field::DeformationField> f =
      options.prior ? field::DeformationField::FromParams(options.prior->config(), AabbOfMeans(st->params.means),
                                                          time_range, options.prior->params())
                    : field::DeformationField::Create(options.config, AabbOfMeans(st->params.means), time_range,
                                                      options.seed);
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
  auto stage = std::unique_ptr<DynamicStage>(new DynamicStage(std::move(*f), std::move(adam), options));
  if (options.extended) {
    if (absl::Status s = stage->AttachExtension(options, /*from_prior=*/true); !s.ok()) return s;
  }
  return stage;
}

absl::Status DynamicStage::AttachExtension(const FieldOptions& options, bool from_prior) {
  // --field extended: the base moves into the extended field; Δ of the token window is one frame
  // on this run's time axis.
  field::ExtendedFieldConfig ec = *options.extended;
  const field::FieldTimeRange& range = field_.time_range();
  const double span_us = static_cast<double>(range.end_us - range.start_us);
  if (options.frame_interval_us > 0) {
    ec.window_dt =
        span_us > 0 ? std::min(2.0, (field_.config().full_time_range ? 2.0 : 1.0) * options.frame_interval_us / span_us)
                    : 0.0;
  }
  absl::StatusOr<field::ExtendedField> ext =
      from_prior && options.ext_prior ? ExtendedFromPrior(std::move(field_), ec, *options.ext_prior)
                                      : field::ExtendedField::Create(std::move(field_), ec, options.seed + 0x9e37);
  if (!ext.ok()) return ext.status();
  ext_ = std::make_unique<field::ExtendedField>(std::move(*ext));
  return absl::OkStatus();
}

absl::Status DynamicStage::OrderGaussians(TrainState* st, ThreadPool& pool) const {
  return PermuteRows(st, field::SpatialOrder(field().aabb(), st->params.means.data(), st->size(), nullptr, pool));
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
  const std::string ext_path = ExtendedCheckpointPath(path);
  std::error_code ec;
  if (!options.extended) {
    if (std::filesystem::exists(ext_path, ec)) {
      return absl::FailedPreconditionError(
          absl::StrCat(path, ": the checkpoint is from a --field extended run; resume it with that"));
    }
    return std::unique_ptr<DynamicStage>(new DynamicStage(std::move(ck->field), std::move(ck->adam), options));
  }
  auto stage = std::unique_ptr<DynamicStage>(new DynamicStage(std::move(ck->field), std::move(ck->adam), options));
  if (options.grow_extension) {
    // An S3Gaussian run continued with modules (FieldOptions::grow_extension): they join at their
    // init, which leaves the field's output as it was (gates and the decoder's last layers zero).
    if (std::filesystem::exists(ext_path, ec)) {
      return absl::FailedPreconditionError(
          absl::StrCat(ext_path, ": the checkpoint already has an extension; resume it without growing one"));
    }
    if (absl::Status s = stage->AttachExtension(options, /*from_prior=*/false); !s.ok()) return s;
    stage->ext_deforms_ = fine_iterations;
    stage->extension_from_ = fine_iterations;
    return stage;
  }
  field::ExtAdamState ext_adam;
  absl::StatusOr<field::ExtendedField> ext =
      field::LoadExtendedCheckpoint(ext_path, std::move(stage->field_), &ext_adam);
  if (!ext.ok()) return ext.status();
  if (ext->config().ModulesString() != options.extended->ModulesString()) {
    return absl::FailedPreconditionError(absl::StrCat(ext_path, ": the checkpoint has --field-modules ",
                                                      ext->config().ModulesString(), ", not ",
                                                      options.extended->ModulesString()));
  }
  // The extension's Adam steps from the fine iteration it joined at (0 unless grown on a resume).
  if (options.extension_from_fine_iteration < 0 || options.extension_from_fine_iteration > fine_iterations ||
      ext_adam.step != fine_iterations - options.extension_from_fine_iteration) {
    return absl::FailedPreconditionError(
        absl::StrCat(ext_path, ": ", ext_adam.step, " fine iterations, the Gaussian checkpoint ", fine_iterations,
                     options.extension_from_fine_iteration > 0
                         ? absl::StrCat(" with the extension grown at ", options.extension_from_fine_iteration)
                         : ""));
  }
  stage->ext_ = std::make_unique<field::ExtendedField>(std::move(*ext));
  stage->ext_adam_ = std::move(ext_adam);
  stage->ext_deforms_ = fine_iterations;
  stage->extension_from_ = options.extension_from_fine_iteration;
  return stage;
}

absl::Status DynamicStage::SaveCheckpoint(const std::string& path) {
  if (absl::Status s = SyncHost(); !s.ok()) return s;
  // The scene directory's field_ext.bin follows the checkpoints (the trainer writes field.bin from
  // field() after the last one); a plain field's run removes an older run's extension.
  const std::string scene_ext =
      (std::filesystem::path(path).parent_path() / field::kExtendedFieldFileName).string();
  if (!ext_) {
    std::error_code ec;
    std::filesystem::remove(scene_ext, ec);
    return field::SaveFieldCheckpoint(field_, adam_, path);
  }
  if (absl::Status s = field::SaveFieldCheckpoint(ext_->base(), adam_, path); !s.ok()) return s;
  if (absl::Status s = field::SaveExtendedCheckpoint(*ext_, ext_adam_, ExtendedCheckpointPath(path)); !s.ok()) {
    return s;
  }
  return field::SaveExtendedField(*ext_, scene_ext);
}

std::shared_ptr<const field::DeformationField> DynamicStage::SceneField() const {
  if (ext_) return field::ShareWithExtension(*ext_);
  return std::make_shared<const field::DeformationField>(field_);
}

std::string FineStageTimings::Summary() const {
  const double n = static_cast<double>(std::max<int64_t>(iterations, 1));
  if (optimizer_on_device) {
    return absl::StrFormat(
        "fine stage: %d iterations, ms per iteration: field forward %.1f, field backward %.1f, plane "
        "regularisers + field Adam on the device %.1f",
        iterations, deform_ms / n, backward_ms / n, adam_ms / n);
  }
  return absl::StrFormat(
      "fine stage: %d iterations, ms per iteration: field forward %.1f, field backward %.1f, plane "
      "regularisers %.1f, gradient check %.1f, field Adam %.1f, parameter upload %.1f",
      iterations, deform_ms / n, backward_ms / n, regularizers_ms / n, gradient_check_ms / n, adam_ms / n,
      upload_ms / n);
}

std::string ExtendedCheckpointPath(const std::string& field_checkpoint_path) {
  std::string p = field_checkpoint_path;
  if (p.size() >= 4 && p.compare(p.size() - 4, 4, ".bin") == 0) p.resize(p.size() - 4);
  return p + "_ext.bin";
}

absl::StatusOr<GaussianParamsView> DynamicStage::Deform(const TrainState& st, int active_degree, int64_t time_us,
                                                        ThreadPool& pool) {
  const auto t0 = Clock::now();
  absl::StatusOr<GaussianParamsView> view =
      ext_ ? DeformExtended(st, active_degree, time_us, pool) : DeformBase(st, active_degree, time_us, pool);
  timings_.deform_ms += MsSince(t0);
  return view;
}

absl::StatusOr<GaussianParamsView> DynamicStage::DeformBase(const TrainState& st, int active_degree, int64_t time_us,
                                                            ThreadPool& pool) {
  field::CanonicalView c{st.size(), st.params.means.data(), st.params.sh.data()};
  if (use_vulkan_ && !vk_) {  // here, after Begin/Resume/prior have set the parameters
    absl::StatusOr<std::unique_ptr<field::VulkanFieldDevice>> vk = field::VulkanFieldDevice::Create(field_);
    if (!vk.ok()) return vk.status();
    vk_ = std::move(*vk);
    optimizer_on_device_ = optimizer_place_ == FieldOptimizerPlace::kDevice ||
                           (optimizer_place_ == FieldOptimizerPlace::kAuto && !vk_->is_cpu_device());
    // A resumed Adam continues from its moments; a fresh one starts at 0 there. A device without
    // room for the moments keeps the host optimiser unless the device one was asked for.
    if (optimizer_on_device_) {
      const absl::Status s =
          adam_.step > 0 ? vk_->base()->SetAdamMoments(adam_.m, adam_.v) : vk_->base()->PrepareOptimizer();
      if (!s.ok() && optimizer_place_ == FieldOptimizerPlace::kDevice) return s;
      if (!s.ok()) {
        LOG(WARNING) << "fine stage: the field's optimiser stays on the host (" << s << ")";
        optimizer_on_device_ = false;
      }
    }
    timings_.optimizer_on_device = optimizer_on_device_;
    LOG(INFO) << "fine stage: the field runs on Vulkan (" << vk_->device_description() << ")"
              << (optimizer_on_device_ ? ", its regularisers and Adam too" : "");
  }
  const absl::Status deformed =
      vk_ ? field::VulkanDeformScene(*vk_->base(), field_, field_.TimeCoordinate(time_us), c, pool, &deformed_)
          : field::DeformScene(field_, field_.TimeCoordinate(time_us), c, pool, *ws_, &deformed_);
  if (!deformed.ok()) return deformed;
  // Colour direction: the engine takes it from the means it renders, i.e. the deformed ones
  // (S3Gaussian uses the canonical xyz, spec quirk 4).
  return field::DeformedParamsView(ParamsView(st, active_degree), deformed_);
}

absl::StatusOr<double> DynamicStage::Backward(const TrainState& st, int active_degree, int64_t fine_iteration,
                                              GaussianGrads* grads, ThreadPool& pool) {
  ++timings_.iterations;
  if (ext_) return BackwardExtended(st, active_degree, fine_iteration, grads, pool);
  field::CanonicalView c{st.size(), st.params.means.data(), st.params.sh.data()};
  if (deformed_.dx.size() != c.n * 3) return absl::InternalError("DynamicStage::Backward without a matching Deform");
  if (vk_ && optimizer_on_device_) return BackwardOnDevice(st, active_degree, fine_iteration, grads, pool);
  auto t0 = Clock::now();
  if (d_field_.size() == field_.layout().total) {
    std::fill(d_field_.begin(), d_field_.end(), 0.0f);
  } else {
    d_field_.assign(field_.layout().total, 0.0f);
  }
  absl::StatusOr<field::DeformLosses> dl =
      vk_ ? field::VulkanDeformBackward(*vk_->base(), field_, c, deformed_, active_degree, hyper_, pool, grads, &d_field_,
                                        &vk_scratch_)
          : field::DeformBackward(field_, c, deformed_, active_degree, hyper_, pool, *ws_, grads, &d_field_);
  if (!dl.ok()) return dl.status();
  timings_.backward_ms += MsSince(t0);
  const absl::StatusOr<double> reg =
      RegularizeAndStepBaseField(hyper_, fine_iteration, st.extent, pool, field_, d_field_, &adam_, &timings_);
  if (!reg.ok()) return reg.status();
  if (vk_) {
    t0 = Clock::now();
    if (absl::Status s = vk_->UpdateParams(field_.params()); !s.ok()) return s;
    timings_.upload_ms += MsSince(t0);
  }
  return dl->weighted + *reg;
}

absl::StatusOr<double> DynamicStage::BackwardOnDevice(const TrainState& st, int active_degree,
                                                      int64_t fine_iteration, GaussianGrads* grads, ThreadPool& pool) {
  field::CanonicalView c{st.size(), st.params.means.data(), st.params.sh.data()};
  auto t0 = Clock::now();
  absl::StatusOr<field::DeformLosses> dl = field::VulkanDeformBackward(*vk_->base(), field_, c, deformed_,
                                                                       active_degree, hyper_, pool, grads, nullptr,
                                                                       &vk_scratch_);
  if (!dl.ok()) return dl.status();
  timings_.backward_ms += MsSince(t0);
  t0 = Clock::now();
  // adam_.step counts as FieldAdamStep's does (its moments live on the device until SyncHost).
  absl::StatusOr<field::RegularizerLosses> reg = vk_->base()->RegularizeAndStep(
      PlaneRegularizerWeights(hyper_), field::FieldLearningRates(hyper_, fine_iteration, st.extent), adam_.step + 1);
  if (!reg.ok()) return reg.status();
  ++adam_.step;
  host_stale_ = true;
  timings_.adam_ms += MsSince(t0);
  return dl->weighted + reg->weighted;
}

absl::Status DynamicStage::SyncHost() {
  if (!host_stale_) return absl::OkStatus();
  const size_t total = field_.layout().total;
  if (absl::Status s = vk_->base()->ReadParams(field_.mutable_params()); !s.ok()) return s;
  adam_.m.resize(total);
  adam_.v.resize(total);
  if (absl::Status s = vk_->base()->ReadAdamMoments(adam_.m, adam_.v); !s.ok()) return s;
  host_stale_ = false;
  return absl::OkStatus();
}

namespace {
constexpr char kFieldCheckpointPrefix[] = "checkpoint_field_";
bool IsFieldCheckpointName(const std::string& name) { return name.rfind(kFieldCheckpointPrefix, 0) == 0; }
}  // namespace

std::string FieldCheckpointPath(const std::string& out_dir, int64_t iteration) {
  return (std::filesystem::path(out_dir) / absl::StrCat(kFieldCheckpointPrefix, iteration, ".bin")).string();
}

FieldCheckpointsFound FindFieldCheckpoints(const std::string& out_dir) {
  FieldCheckpointsFound found;
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator(out_dir, ec)) {
    const std::string path = e.path().string();
    if (!IsFieldCheckpointName(e.path().filename().string())) continue;
    // ExtendedCheckpointPath's suffix.
    (path.size() > 8 && path.compare(path.size() - 8, 8, "_ext.bin") == 0 ? found.extended : found.base) = true;
  }
  return found;
}

void RemoveFieldCheckpoints(const std::string& out_dir, int64_t keep_iteration) {
  std::error_code ec;
  const std::string keep = keep_iteration >= 0 ? FieldCheckpointPath(out_dir, keep_iteration) : "";
  std::vector<std::filesystem::path> doomed;
  for (const auto& e : std::filesystem::directory_iterator(out_dir, ec)) {
    const std::string name = e.path().filename().string();
    if (IsFieldCheckpointName(name) && e.path().string() != keep &&
        (keep.empty() || e.path().string() != ExtendedCheckpointPath(keep))) {
      doomed.push_back(e.path());
    }
  }
  for (const auto& p : doomed) std::filesystem::remove(p, ec);
}

absl::StatusOr<GaussianStore> DeformedStore(const field::DeformationField& f, const GaussianStore& canonical,
                                            int64_t time_us, ThreadPool& pool) {
  // A field loaded with its extension (LoadSceneField, DynamicStage::SceneField).
  if (std::shared_ptr<const field::ExtendedField> ext = field::ExtensionOf(f)) {
    return field::ExtDeformedStore(*ext, canonical, time_us, pool);
  }
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
  // --field extended: DIR/field_ext.bin (its base checksum ties it to this field.bin).
  const std::string ext_path = (std::filesystem::path(dir) / field::kExtendedFieldFileName).string();
  if (std::filesystem::exists(ext_path)) {
    absl::StatusOr<field::ExtendedField> ext = field::LoadExtendedField(ext_path, std::move(*f));
    if (!ext.ok()) return ext.status();
    return field::ShareWithExtension(std::move(*ext));
  }
  return std::make_shared<const field::DeformationField>(std::move(*f));
}

// --field extended: the fine step through field::ExtendedField (extended_deform.h).
absl::StatusOr<GaussianParamsView> DynamicStage::DeformExtended(const TrainState& st, int active_degree,
                                                                int64_t time_us, ThreadPool& pool) {
  if (!ext_ws_) ext_ws_ = std::make_unique<field::ExtWorkspace>();
  field::ExtPass pass;
  pass.time_coord = ext_->base().TimeCoordinate(time_us);
  pass.training = true;
  // A new ε per fine iteration, reproducible from the stage's seed and the iteration (resume).
  pass.noise_seed = ext_noise_seed_ * 0x9e3779b97f4a7c15ull + static_cast<uint64_t>(++ext_deforms_);
  const field::ExtCanonicalView c{st.size(), st.params.means.data(), st.params.sh.data(),
                                  st.params.log_scales.data(), st.params.rotations.data(),
                                  st.params.opacity_logits.data()};
  if (use_vulkan_ && !vk_) {  // here, after Begin/Resume/prior have set the parameters
    absl::StatusOr<std::unique_ptr<field::VulkanFieldDevice>> vk = field::VulkanFieldDevice::Create(*ext_);
    if (!vk.ok()) return vk.status();
    vk_ = std::move(*vk);
    ext_eval_ = vk_->ext_evaluator();
    LOG(INFO) << "fine stage: the extended field runs on Vulkan (" << vk_->device_description() << ")";
  }
  if (absl::Status s = field::DeformSceneExt(*ext_, pass, c, pool, *ext_ws_, &ext_deformed_, ext_eval_); !s.ok()) {
    return s;
  }
  return field::ExtDeformedParamsView(ParamsView(st, active_degree), ext_deformed_);
}

absl::StatusOr<double> DynamicStage::BackwardExtended(const TrainState& st, int active_degree,
                                                      int64_t fine_iteration, GaussianGrads* grads,
                                                      ThreadPool& pool) {
  const field::ExtCanonicalView c{st.size(), st.params.means.data(), st.params.sh.data(),
                                  st.params.log_scales.data(), st.params.rotations.data(),
                                  st.params.opacity_logits.data()};
  if (ext_deformed_.dx.size() != c.n * 3) {
    return absl::InternalError("DynamicStage::Backward without a matching Deform");
  }
  field::DeformationField& base = ext_->mutable_base();
  if (d_field_.size() == base.layout().total) {
    std::fill(d_field_.begin(), d_field_.end(), 0.0f);
  } else {
    d_field_.clear();  // DeformBackwardExt allocates it on huge pages
  }
  std::fill(d_ext_.begin(), d_ext_.end(), 0.0f);
  auto t0 = Clock::now();
  absl::StatusOr<field::ExtDeformLosses> dl =
      field::DeformBackwardExt(*ext_, c, ext_deformed_, active_degree, hyper_,
                               field::ExtKlBeta(ext_->config(), fine_iteration), pool, *ext_ws_, grads, &d_field_,
                               &d_ext_, ext_eval_);
  if (!dl.ok()) return dl.status();
  timings_.backward_ms += MsSince(t0);
  t0 = Clock::now();
  if (absl::Status s = CheckFiniteNetworkGradient(fine_iteration, "field extension", d_ext_.data(), d_ext_.size(), pool);
      !s.ok()) {
    return s;
  }
  timings_.gradient_check_ms += MsSince(t0);
  const absl::StatusOr<double> reg =
      RegularizeAndStepBaseField(hyper_, fine_iteration, st.extent, pool, base, d_field_, &adam_, &timings_);
  if (!reg.ok()) return reg.status();
  t0 = Clock::now();
  field::ExtAdamStep(ext_->mutable_params().data(), d_ext_.data(), d_ext_.size(), &ext_adam_,
                     field::ExtNetworkLr(ext_hyper_, fine_iteration));
  timings_.adam_ms += MsSince(t0);
  if (vk_) {
    t0 = Clock::now();
    if (absl::Status s = vk_->UpdateParams(base.params(), ext_->params()); !s.ok()) return s;
    timings_.upload_ms += MsSince(t0);
  }
  return dl->weighted + *reg;
}

}  // namespace streetsim::train
