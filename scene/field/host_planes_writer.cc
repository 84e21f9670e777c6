#include "scene/field/host_planes_writer.h"

#include "absl/strings/str_cat.h"

namespace streetsim::field {

absl::Status HostPlanesWriter::WriteAt(int64_t time_us, DeviceScene* scene) {
  if (scene == nullptr) return absl::InvalidArgumentError("no scene to write the serving form into");
  absl::StatusOr<ScenePlanes> planes = engine_.WritablePlanes(scene);
  if (!planes.ok()) {
    return absl::FailedPreconditionError(
        absl::StrCat("the engine keeps no writable planes of the scene: ", planes.status().message()));
  }
  return form_.WritePlanesAt(time_us, *planes, pool_);
}

absl::StatusOr<std::unique_ptr<DeviceSceneWriter>> HostPlanesWriterFor(Engine& engine, ServedScene& served,
                                                                        ThreadPool& pool) {
  auto* form = dynamic_cast<ServingForm*>(&served);
  if (form == nullptr || engine.backend() != Backend::kCpu || form->num_dynamic() == 0) {
    return std::unique_ptr<DeviceSceneWriter>();
  }
  return std::unique_ptr<DeviceSceneWriter>(std::make_unique<HostPlanesWriter>(engine, *form, pool));
}

}  // namespace streetsim::field
