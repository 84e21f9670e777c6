#include "render/vulkan/field/vulkan_field_device.h"

#include "render/vulkan/field/ext/vulkan_extended_field.h"

namespace streetsim::field {

VulkanFieldDevice::~VulkanFieldDevice() = default;

absl::StatusOr<std::unique_ptr<VulkanFieldDevice>> VulkanFieldDevice::Create(const DeformationField& field,
                                                                              const VulkanFieldOptions& options) {
  if (std::shared_ptr<const ExtendedField> ext = ExtensionOf(field)) return Create(*ext, options);
  absl::StatusOr<std::unique_ptr<VulkanField>> base = VulkanField::Create(field, options);
  if (!base.ok()) return base.status();
  std::unique_ptr<VulkanFieldDevice> d(new VulkanFieldDevice());
  d->base_ = std::move(*base);
  return d;
}

absl::StatusOr<std::unique_ptr<VulkanFieldDevice>> VulkanFieldDevice::Create(const ExtendedField& field,
                                                                              const VulkanFieldOptions& options) {
  absl::StatusOr<std::unique_ptr<VulkanExtendedField>> ext = VulkanExtendedField::Create(field, options);
  if (!ext.ok()) return ext.status();
  std::unique_ptr<VulkanFieldDevice> d(new VulkanFieldDevice());
  d->ext_ = std::move(*ext);
  VulkanExtendedField* f = d->ext_.get();  // owned by d, which outlives its evaluator
  d->ext_eval_.forward = [f](const ExtPass& p, const ExtInputs<float>& in, const ExtOutputs<float>& out) {
    return f->Forward(p, in, out);
  };
  d->ext_eval_.backward = [f](const ExtPass& p, const ExtInputs<float>& in, const ExtOutputGrads<float>& d_out,
                              double kl_weight, const ExtInputGrads<float>& grads) {
    return f->Backward(p, in, d_out, kl_weight, grads);
  };
  return d;
}

absl::Status VulkanFieldDevice::Forward(const FieldQuery& query, std::span<const float> means, std::vector<float>* dx,
                                        std::vector<float>* dsh) {
  if (!base_) return absl::FailedPreconditionError("VulkanFieldDevice::Forward on the extended field");
  return base_->Forward(query, means, dx, dsh);
}

absl::StatusOr<double> VulkanFieldDevice::ForwardExt(const ExtPass& pass, const ExtInputs<float>& in,
                                                     const ExtOutputs<float>& out) {
  if (!ext_) return absl::FailedPreconditionError("VulkanFieldDevice::ForwardExt on S3Gaussian's field");
  return ext_->Forward(pass, in, out);
}

absl::Status VulkanFieldDevice::UpdateParams(std::span<const float> base_params, std::span<const float> ext_params) {
  return ext_ ? ext_->UpdateParams(base_params, ext_params) : base_->UpdateParams(base_params);
}

std::string VulkanFieldDevice::device_description() const {
  return ext_ ? ext_->device_description() : base_->device_description();
}

bool VulkanFieldDevice::is_cpu_device() const { return ext_ ? ext_->is_cpu_device() : base_->is_cpu_device(); }

}  // namespace streetsim::field
