#include "server/scene_loading.h"

#include <filesystem>
#include <optional>
#include <system_error>
#include <vector>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "scene/field/extended/extended_serving.h"
#include "render/vulkan/field/vulkan_serving.h"
#include "scene/field/extended/extended_io.h"
#include "scene/field/field_io.h"
#include "scene/field/host_planes_writer.h"
#include "scene/gaussians/ply_io.h"
#include "scene/eval/lidar_eval.h"
#include "scene/eval/served_scene.h"
#include "scene/train/trainer.h"
#include "server/dynamic_scene_field.h"

namespace streetsim::server {
namespace fs = std::filesystem;

absl::StatusOr<SceneManifest> ReadSceneDirManifest(const std::string& manifest_path) {
  absl::StatusOr<SceneManifest> m = SceneManifest{};
  if (!manifest_path.empty() && fs::exists(manifest_path)) {
    m = ReadSceneManifest(manifest_path);
  } else {
    m->cameras = DefaultRig();
  }
  // A trained scene's learned sky colour (train_meta.json beside scene.ply).
  if (m.ok() && !manifest_path.empty()) {
    const fs::path dir = fs::path(manifest_path).parent_path();
    if (fs::exists(dir / "train_meta.json")) {
      absl::StatusOr<train::SceneMeta> meta = train::ReadSceneMeta(dir.string());
      if (!meta.ok()) return meta.status();
      m->background = meta->background;
    }
  }
  return m;
}

namespace {

// A status about a scene's field file: `named` (field.bin, or field_ext.bin for an extended field) first.
absl::Status InFieldFile(const fs::path& named, const absl::Status& s) {
  return absl::Status(s.code(), absl::StrCat(named.string(), ": ", s.message()));
}

// The field exactly as trained (field.bin, with `ext_path` the extended field), its static
// Gaussians baked (load.static_skip), on load.field_device. Errors name the field's file.
absl::StatusOr<std::unique_ptr<field::ServedScene>> ExactServedScene(const fs::path& field_path,
                                                                     const fs::path* ext_path, GaussianStore canonical,
                                                                     const SceneLoadOptions& load) {
  const fs::path& named = ext_path ? *ext_path : field_path;
  // Before the field is read: a scene that cannot have one is refused without loading it.
  if (canonical.sh_degree != 3) {
    return InFieldFile(named, absl::FailedPreconditionError(absl::StrCat(
                                  "a field needs SH degree 3 Gaussians, scene.ply has degree ", canonical.sh_degree)));
  }
  absl::StatusOr<field::DeformationField> f = field::LoadField(field_path.string());
  if (!f.ok()) return f.status();  // DATA_LOSS naming the file
  std::optional<train::ExactField> exact;
  if (ext_path) {
    absl::StatusOr<field::ExtendedField> ext = field::LoadExtendedField(ext_path->string(), std::move(*f));
    if (!ext.ok()) return ext.status();  // names field_ext.bin
    exact.emplace(std::move(*ext));
  } else {
    exact.emplace(std::move(*f));
  }
  const bool on_vulkan = load.field_device == train::FieldDevice::kVulkan;
  const field::ServingField::Device vk = on_vulkan ? field::VulkanFieldForward() : field::ServingField::Device{};
  const field::ExtServingField::Device vk_ext =
      on_vulkan ? field::VulkanExtFieldForward() : field::ExtServingField::Device{};
  ThreadPool pool(0);
  absl::StatusOr<std::unique_ptr<field::ServedScene>> s =
      train::MakeExactServedScene(std::move(*exact), std::move(canonical), load.static_skip, pool,
                                  on_vulkan ? train::ServedFieldDevice{&vk, &vk_ext} : train::ServedFieldDevice{});
  if (!s.ok()) return InFieldFile(named, s.status());
  return s;
}

// The serving form of the scene's field from DIR/field.serving, or built from the exact field
// (once; then cached there) when that cache is missing, stale or damaged; the exact field when
// the form misses its error bound.
absl::StatusOr<std::unique_ptr<field::ServedScene>> ServingFormOf(const fs::path& field_path, const fs::path* ext_path,
                                                                  GaussianStore canonical,
                                                                  const SceneLoadOptions& load) {
  // Called at most once (LoadServedScene), so the Gaussians move in.
  auto make_exact = [&]() { return ExactServedScene(field_path, ext_path, std::move(canonical), load); };
  return train::LoadServedScene(field_path.parent_path().string(), make_exact, load.serving_form, load.static_skip);
}

}  // namespace

absl::StatusOr<std::shared_ptr<LoadedScene>> LoadSceneFile(const std::string& path, const SceneUploader& upload,
                                                           const SceneLoadOptions& load) {
  absl::StatusOr<GaussianStore> store = ReadGaussianPly(path);
  if (!store.ok()) return store.status();
  auto loaded = std::make_shared<LoadedScene>();
  loaded->num_gaussians = store->size();
  if (store->size() > 0) {
    Eigen::Map<const Eigen::Matrix<float, 3, Eigen::Dynamic>> m(store->means.data(), 3, store->size());
    loaded->min_m = m.rowwise().minCoeff().cast<double>();
    loaded->max_m = m.rowwise().maxCoeff().cast<double>();
  }
  absl::StatusOr<std::optional<std::vector<float>>> reflectance = train::ReadPlyReflectance(path, store->size());
  if (!reflectance.ok()) return reflectance.status();
  // Its actors: a damaged set, or one of another scene.ply, is refused naming the file rather
  // than edited with the wrong rows.
  std::error_code actors_ec;
  if (fs::path(path).filename() == "scene.ply" &&
      fs::exists(fs::path(path).parent_path() / actors::kActorsJson, actors_ec)) {
    absl::StatusOr<actors::ActorSet> set = actors::ReadActorSet(fs::path(path).parent_path().string());
    if (!set.ok()) return set.status();
    if (set->scene_gaussians != store->size()) {
      return absl::DataLossError(absl::StrCat((fs::path(path).parent_path() / actors::kActorsJson).string(),
                                              ": its scene had ", set->scene_gaussians, " Gaussians, scene.ply has ",
                                              store->size()));
    }
    loaded->actors = std::make_shared<const actors::ActorSet>(std::move(*set));
  }
  // A trained dynamic scene: DIR/field.bin beside DIR/scene.ply (bare .ply files are static).
  const fs::path field_path = fs::path(path).parent_path() / field::kFieldFileName;
  std::error_code ec;
  if (fs::path(path).filename() == "scene.ply" && fs::exists(field_path, ec)) {
    // --field extended: DIR/field_ext.bin, checked against this field.bin as the CLI's
    // train::LoadSceneField does (damage, another run's file: DATA_LOSS naming field_ext.bin).
    const fs::path ext_path = fs::path(path).parent_path() / field::kExtendedFieldFileName;
    const bool extended = fs::exists(ext_path, ec);
    const fs::path* ext = extended ? &ext_path : nullptr;
    absl::StatusOr<std::unique_ptr<field::ServedScene>> served =
        load.exact_field ? ExactServedScene(field_path, ext, std::move(*store), load)
                         : ServingFormOf(field_path, ext, std::move(*store), load);
    if (!served.ok()) return served.status();  // naming the file
    // The form's writer for the engine it renders on: the Vulkan kernel when the field's device
    // is Vulkan too, else the cpu engine's planes (null for any other pair: the host path).
    const bool vulkan_field = load.field_device == train::FieldDevice::kVulkan;
    DeviceWriterMaker writer = [vulkan_field](Engine& engine, field::ServedScene& served, ThreadPool& pool) {
      absl::StatusOr<std::unique_ptr<field::DeviceSceneWriter>> w =
          vulkan_field ? field::DeviceWriterFor(engine, served) : std::unique_ptr<field::DeviceSceneWriter>();
      if (!w.ok() || *w) return w;
      return field::HostPlanesWriterFor(engine, served, pool);
    };
    absl::StatusOr<std::unique_ptr<DynamicSceneField>> dynamic =
        DynamicSceneField::Create(std::move(*served), std::move(*reflectance), upload, std::move(writer));
    if (!dynamic.ok()) return InFieldFile(extended ? ext_path : field_path, dynamic.status());
    loaded->field = std::move(*dynamic);
    return loaded;
  }
  absl::StatusOr<std::unique_ptr<DeviceScene>> device = upload(*store);
  if (!device.ok()) return device.status();
  // The host copy serves LiDAR sweeps (render/lidar takes a GaussianStore).
  auto host = std::make_shared<HostScene>();
  host->store = std::move(*store);
  host->reflectance = std::move(*reflectance);
  loaded->field = std::make_unique<StaticSceneField>(std::move(*device), std::move(host));
  return loaded;
}

}  // namespace streetsim::server
