#include "render/vulkan/field/vulkan_serving.h"

#include <memory>

#include "render/common/log.h"
#include "render/vulkan/field/vulkan_field_device.h"
#include "render/vulkan/field/vulkan_serving_form.h"
#include "scene/field/serving_form.h"

namespace streetsim::field {

namespace {

// The device field behind a scene's hook (VulkanFieldDevice, as the trainer uses it):
// std::function wants a copyable callable, the field is created on the first call.
using LazyDevice = std::shared_ptr<std::unique_ptr<VulkanFieldDevice>>;

template <typename Source>
absl::Status EnsureCreated(const LazyDevice& device, const Source& field, const VulkanFieldOptions& options) {
  if (*device) return absl::OkStatus();
  absl::StatusOr<std::unique_ptr<VulkanFieldDevice>> created = VulkanFieldDevice::Create(field, options);
  if (!created.ok()) return created.status();
  *device = std::move(*created);
  LOG(INFO) << "serving the field on Vulkan (" << (*device)->device_description() << ")";
  return absl::OkStatus();
}

}  // namespace

ServingField::Device VulkanFieldForward(const VulkanFieldOptions& options) {
  auto device = std::make_shared<std::unique_ptr<VulkanFieldDevice>>();
  return {kVulkanServingDevice,
          [device, options](const DeformationField& field, const FieldQuery& query, std::span<const float> means,
                            std::vector<float>* dx, std::vector<float>* dsh) -> absl::Status {
            if (absl::Status s = EnsureCreated(device, field, options); !s.ok()) return s;
            return (*device)->Forward(query, means, dx, dsh);
          }};
}

ExtServingField::Device VulkanExtFieldForward(const VulkanFieldOptions& options) {
  auto device = std::make_shared<std::unique_ptr<VulkanFieldDevice>>();
  return {kVulkanServingDevice,
          [device, options](const ExtendedField& field, const ExtPass& pass, const ExtInputs<float>& in,
                            const ExtOutputs<float>& out) -> absl::StatusOr<double> {
            if (absl::Status s = EnsureCreated(device, field, options); !s.ok()) return s;
            return (*device)->ForwardExt(pass, in, out);
          }};
}

absl::StatusOr<std::unique_ptr<DeviceSceneWriter>> DeviceWriterFor(Engine& engine, const ServedScene& served) {
  const auto* form = dynamic_cast<const ServingForm*>(&served);
  if (form == nullptr || engine.backend() != Backend::kVulkan || form->num_dynamic() == 0) {
    return std::unique_ptr<DeviceSceneWriter>();
  }
  absl::StatusOr<std::unique_ptr<VulkanServingForm>> w = VulkanServingForm::Create(engine, *form);
  if (!w.ok()) return w.status();
  LOG(INFO) << "serving form: evaluated on the engine's device (" << (*w)->device_description() << "), "
            << (*w)->device_bytes() / 1e6 << " MB of tables";
  return std::unique_ptr<DeviceSceneWriter>(std::move(*w));
}

void ServeOnVulkan(ServingField& scene, const VulkanFieldOptions& options) {
  ServingField::Device d = VulkanFieldForward(options);
  scene.SetDevice(std::move(d.name), std::move(d.forward));
}

void ServeOnVulkan(ExtServingField& scene, const VulkanFieldOptions& options) {
  ExtServingField::Device d = VulkanExtFieldForward(options);
  scene.SetDevice(std::move(d.name), std::move(d.forward));
}

}  // namespace streetsim::field
