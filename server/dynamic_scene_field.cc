#include "server/dynamic_scene_field.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "render/params_view.h"
#include "render/common/log.h"
#include "scene/field/serving_form.h"

namespace streetsim::server {

absl::StatusOr<std::unique_ptr<DynamicSceneField>> DynamicSceneField::Create(
    std::unique_ptr<field::ServedScene> served, std::optional<std::vector<float>> reflectance,
    const SceneUploader& upload, DeviceWriterMaker make_writer) {
  if (!served) return absl::InvalidArgumentError("no served scene");
  std::unique_ptr<DynamicSceneField> f(new DynamicSceneField());
  f->num_gaussians_ = served->size();
  f->num_dynamic_ = served->num_dynamic();
  f->reflectance_ = std::move(reflectance);
  // One pool per scene: ThreadPool is not reentrant, and At runs under the engine lock, so the
  // field and the renderer never compete for the cores.
  f->pool_ = std::make_unique<ThreadPool>(0);
  f->serving_ = std::move(served);
  // The first upload allocates the device copy (and checks the Gaussians); later timestamps update it.
  absl::StatusOr<const GaussianStore*> first = f->serving_->At(f->serving_->time_range().start_us, *f->pool_);
  if (!first.ok()) return first.status();
  absl::StatusOr<std::unique_ptr<DeviceScene>> device = upload(**first);
  if (!device.ok()) return device.status();
  f->device_ = std::move(*device);
  f->device_evaluation_ = f->serving_->field_evaluations();
  f->timestamps_ = f->serving_->field_evaluations();
  f->counted_time_us_ = f->serving_->time_range().start_us;
  f->evaluations_.store(f->timestamps_);
  f->device_name_ = f->serving_->device();
  f->on_device_.store(f->serving_->device() != "cpu");
  f->make_writer_ = std::move(make_writer);
  return f;
}

int64_t DynamicSceneField::ClampedLocked(int64_t time_us) const {
  // As the served scene clamps, here too: times past either end are one time (one write, one count).
  const field::FieldTimeRange r = serving_->time_range();
  return std::clamp(time_us, r.start_us, std::max(r.start_us, r.end_us));
}

void DynamicSceneField::CountLocked(int64_t time_us) const {
  if (counted_time_us_ == time_us) return;
  ++timestamps_;
  counted_time_us_ = time_us;
  evaluations_.store(timestamps_);
}

absl::StatusOr<const GaussianStore*> DynamicSceneField::EvaluateLocked(int64_t time_us, bool geometry_only) const {
  // Clamps to the log's range; a repeated time coordinate is free.
  const int64_t before = serving_->field_evaluations();
  absl::StatusOr<const GaussianStore*> store =
      geometry_only ? serving_->GeometryAt(time_us, *pool_) : serving_->At(time_us, *pool_);
  if (serving_->field_evaluations() != before) CountLocked(time_us);
  on_device_.store(serving_->device() != "cpu");
  return store;
}

bool DynamicSceneField::WriteOnDeviceLocked(int64_t time_us, Engine& engine) const {
  if (make_writer_) {
    absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>> w = make_writer_(engine, *serving_, *pool_);
    make_writer_ = nullptr;
    if (w.ok()) {
      writer_ = std::move(*w);  // null: nothing for this engine, the host path
      if (writer_) writer_device_ = writer_->device();  // before on_writer_ publishes it to stats()
    } else {
      LOG(WARNING) << "the serving form stays on the host: " << w.status();
    }
    on_writer_.store(writer_ != nullptr);
  }
  if (!writer_) return false;
  if (writer_time_us_ == time_us) return true;
  device_evaluation_ = -1;  // whatever the device copy held, it is the writer's from here
  if (absl::Status s = writer_->WriteAt(time_us, device_.get()); !s.ok()) {
    // The host evaluates and uploads everything from now on (device_evaluation_ -1: a full upload).
    LOG(WARNING) << "the serving form's kernel failed, evaluating on the host from now on: " << s;
    writer_.reset();
    writer_time_us_.reset();
    on_writer_.store(false);
    return false;
  }
  writer_time_us_ = time_us;
  CountLocked(time_us);
  return true;
}

absl::StatusOr<const DeviceScene*> DynamicSceneField::At(int64_t time_us, Engine& engine) const {
  std::lock_guard<std::mutex> lock(mu_);
  time_us = ClampedLocked(time_us);
  if (WriteOnDeviceLocked(time_us, engine)) return device_.get();
  absl::StatusOr<const GaussianStore*> store = EvaluateLocked(time_us);
  if (!store.ok()) return store.status();
  if (serving_->field_evaluations() != device_evaluation_) {
    // In place: the backend keeps its buffers and copies in parallel, checking only what rendering
    // needs (UpdateScene would validate the whole store again and, on the cpu, rebuild every array:
    // most of a 500k-Gaussian step went to allocating, zeroing and copying).
    // Only the moving Gaussians' changed values when the device copy holds an earlier time of this
    // scene (every other value is the same at every time).
    const absl::Status s = device_evaluation_ >= 0
                               ? engine.UpdateSceneRows(ParamsViewOf(**store), serving_->changes(), &device_)
                               : engine.UpdateSceneParams(ParamsViewOf(**store), &device_);
    if (!s.ok()) {
      device_evaluation_ = -1;  // the device copy is in an unknown state: update on the next call
      return absl::InternalError(absl::StrCat("uploading the deformed scene failed: ", s.message()));
    }
    device_evaluation_ = serving_->field_evaluations();
  }
  return device_.get();
}

absl::StatusOr<std::shared_ptr<const HostScene>> DynamicSceneField::HostAt(int64_t time_us) const {
  std::lock_guard<std::mutex> lock(mu_);
  return HostLocked(time_us, false);
}

absl::StatusOr<std::shared_ptr<const HostScene>> DynamicSceneField::GeometryAt(int64_t time_us) const {
  std::lock_guard<std::mutex> lock(mu_);
  return HostLocked(time_us, true);
}

absl::StatusOr<std::shared_ptr<const HostScene>> DynamicSceneField::HostLocked(int64_t time_us,
                                                                               bool geometry_only) const {
  absl::StatusOr<const GaussianStore*> store = EvaluateLocked(ClampedLocked(time_us), geometry_only);
  if (!store.ok()) return store.status();
  if (serving_->field_evaluations() != host_evaluation_) {
    // A view of the serving field's Gaussians (no copy of 500k Gaussians per time); a new
    // generation tells the LiDAR renderer to upload again.
    if (!host_) {
      host_ = std::make_shared<HostScene>();
      host_->reflectance = reflectance_;
    }
    host_->view = *store;
    host_->previous_generation = host_evaluation_ >= 0 ? host_->generation : 0;
    host_->change = serving_->changes();
    host_->generation = HostScene::NewHostSceneGeneration();
    host_evaluation_ = serving_->field_evaluations();
  }
  return std::shared_ptr<const HostScene>(host_);
}

FieldStats DynamicSceneField::stats() const {
  const auto* form = dynamic_cast<const field::ServingForm*>(serving_.get());
  return {true,
          num_dynamic_,
          evaluations_.load(),
          on_writer_.load() ? writer_device_
          : on_device_.load() ? device_name_
                              : std::string("cpu"),
          form ? "form" : "exact",
          form ? form->error().max[0] : 0.0};
}

}  // namespace streetsim::server
