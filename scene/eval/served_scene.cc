#include "scene/eval/served_scene.h"

#include <filesystem>
#include <memory>
#include <utility>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/extended/extended_serving.h"
#include "scene/field/field_io.h"
#include "scene/field/serving_form_io.h"

namespace streetsim::train {
namespace {

// Checked before a field is copied or analysed: a served field deforms SH degree 3 Gaussians.
absl::Status CheckCanonical(const GaussianStore& canonical) {
  if (canonical.sh_degree == 3) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
}

}  // namespace

absl::StatusOr<std::shared_ptr<field::ServedScene>> MakeServedScene(
    std::shared_ptr<const field::DeformationField> f, const GaussianStore& canonical,
    const field::StaticSkipOptions& options, ThreadPool* analysis_pool) {
  absl::StatusOr<std::unique_ptr<field::ServedScene>> s = MakeExactServedScene(std::move(f), canonical, options,
                                                                               analysis_pool);
  if (!s.ok()) return s.status();
  return std::shared_ptr<field::ServedScene>(std::move(*s));
}

absl::StatusOr<std::unique_ptr<field::ServedScene>> MakeExactServedScene(ExactField f, GaussianStore canonical,
                                                                         const field::StaticSkipOptions& options,
                                                                         ThreadPool& pool,
                                                                         const ServedFieldDevice& device) {
  if (absl::Status s = CheckCanonical(canonical); !s.ok()) return s;
  if (auto* ext = std::get_if<field::ExtendedField>(&f)) {
    absl::StatusOr<std::unique_ptr<field::ExtServingField>> s =
        field::ExtServingField::Create(std::move(*ext), std::move(canonical), options, pool, device.extended);
    if (!s.ok()) return s.status();
    return std::unique_ptr<field::ServedScene>(std::move(*s));
  }
  absl::StatusOr<field::ServingField> s = field::ServingField::Create(
      std::get<field::DeformationField>(std::move(f)), std::move(canonical), options, pool, device.field);
  if (!s.ok()) return s.status();
  return std::unique_ptr<field::ServedScene>(std::make_unique<field::ServingField>(std::move(*s)));
}

absl::StatusOr<std::unique_ptr<field::ServedScene>> MakeExactServedScene(
    std::shared_ptr<const field::DeformationField> f, const GaussianStore& canonical,
    const field::StaticSkipOptions& options, ThreadPool* analysis_pool) {
  if (!f) return absl::InvalidArgumentError("a served scene needs a field (the scene has no field.bin)");
  if (absl::Status s = CheckCanonical(canonical); !s.ok()) return s;
  std::unique_ptr<ThreadPool> own;
  if (!analysis_pool) own = std::make_unique<ThreadPool>(0);
  std::shared_ptr<const field::ExtendedField> ext = field::ExtensionOf(*f);
  return MakeExactServedScene(ext ? ExactField(*ext) : ExactField(*f), canonical, options,
                              analysis_pool ? *analysis_pool : *own);
}

absl::StatusOr<std::unique_ptr<field::ServedScene>> LoadServedScene(
    const std::string& dir, const std::function<absl::StatusOr<std::unique_ptr<field::ServedScene>>()>& make_exact,
    const field::ServingFormOptions& form, const field::StaticSkipOptions& skip, ThreadPool* pool) {
  const std::filesystem::path d(dir);
  const std::vector<std::string> sources = {(d / "scene.ply").string(), (d / field::kFieldFileName).string(),
                                            (d / field::kExtendedFieldFileName).string()};
  absl::StatusOr<uint64_t> key = field::ServingFormSourceKey(sources, form, skip);
  if (!key.ok()) return key.status();
  std::unique_ptr<ThreadPool> own;
  if (!pool) own = std::make_unique<ThreadPool>(0);
  absl::StatusOr<field::CachedServingForm> cached = field::LoadOrBuildServingForm(
      (d / field::kServingFormFileName).string(), *key, make_exact, form, pool ? *pool : *own);
  if (!cached.ok()) return cached.status();
  if (cached->within_bound(form)) return std::unique_ptr<field::ServedScene>(std::move(cached->form));
  LOG(WARNING) << dir << ": the serving form's p99 position error, "
               << cached->form->error().position_p99_m * 1000 << " mm with " << cached->form->segments()
               << " segments, is above " << form.max_position_error_m * 1000
               << " mm: serving the exact field";
  if (cached->exact) return std::move(cached->exact);
  return make_exact();
}

absl::StatusOr<SceneForView> MakeServedSceneForView(Engine& engine, std::shared_ptr<field::ServedScene> served) {
  if (!served) return absl::InvalidArgumentError("no served scene");
  auto pool = std::make_shared<ThreadPool>(0);
  auto scene = std::make_shared<std::unique_ptr<DeviceScene>>();
  Engine* e = &engine;
  return SceneForView([=](const View& v) -> absl::StatusOr<const DeviceScene*> {
    absl::StatusOr<const GaussianStore*> g = served->At(v.time_us, *pool);
    if (!g.ok()) return g.status();
    if (absl::Status s = e->UpdateScene(**g, scene.get()); !s.ok()) return s;
    return scene->get();
  });
}

StoreAtTime MakeServedStoreAtTime(std::shared_ptr<field::ServedScene> served) {
  auto pool = std::make_shared<ThreadPool>(0);
  return [served, pool](int64_t time_us) -> absl::StatusOr<GaussianStore> {
    absl::StatusOr<const GaussianStore*> g = served->At(time_us, *pool);
    if (!g.ok()) return g.status();
    return **g;
  };
}

}  // namespace streetsim::train
