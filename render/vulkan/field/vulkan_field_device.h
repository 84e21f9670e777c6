// The deformation field on a Vulkan device, as both its users take it: the trainer's fine stage
// (scene/train/dynamic_stage.cc) and the server's served scenes (vulkan_serving.h's hooks). One
// object per field: S3Gaussian's field runs on a VulkanField, the extended field on a
// VulkanExtendedField (its base included); which one follows from the field it is made from, so
// that neither user builds the kernels' classes itself.
//
// Not thread-safe: one caller at a time (as the classes it holds).
#pragma once

#include <memory>
#include <span>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/vulkan/field/vulkan_field.h"
#include "scene/field/deformation_field.h"
#include "scene/field/extended/extended_deform.h"
#include "scene/field/extended/extended_field.h"

namespace streetsim::field {

class VulkanExtendedField;

class VulkanFieldDevice {
 public:
  // S3Gaussian's field, or (ExtensionOf(field) set: a field loaded or shared with its extension)
  // the extended one. Uploads the parameters. The device's errors (none, out of memory) as the
  // classes give them.
  static absl::StatusOr<std::unique_ptr<VulkanFieldDevice>> Create(const DeformationField& field,
                                                                   const VulkanFieldOptions& options = {});
  static absl::StatusOr<std::unique_ptr<VulkanFieldDevice>> Create(const ExtendedField& field,
                                                                    const VulkanFieldOptions& options = {});
  ~VulkanFieldDevice();
  VulkanFieldDevice(const VulkanFieldDevice&) = delete;
  VulkanFieldDevice& operator=(const VulkanFieldDevice&) = delete;

  bool extended() const { return ext_ != nullptr; }
  // S3Gaussian's field (null for the extended one): Forward / Backward and the optimiser on the
  // device (VulkanField::RegularizeAndStep), which only this field has.
  VulkanField* base() { return base_.get(); }
  // The extended field's forward and backward as the cpu composition takes them (DeformSceneExt,
  // DeformBackwardExt); empty functions for S3Gaussian's field.
  const ExtEvaluator& ext_evaluator() const { return ext_eval_; }
  // Δ of S3Gaussian's field at `means` (VulkanField::Forward); FailedPrecondition on the extended one.
  absl::Status Forward(const FieldQuery& query, std::span<const float> means, std::vector<float>* dx,
                       std::vector<float>* dsh);
  // The extended field's outputs (VulkanExtendedField::Forward); FailedPrecondition on S3Gaussian's.
  absl::StatusOr<double> ForwardExt(const ExtPass& pass, const ExtInputs<float>& in, const ExtOutputs<float>& out);

  // Re-uploads every parameter after a step on the host (ext_params: empty for S3Gaussian's field).
  absl::Status UpdateParams(std::span<const float> base_params, std::span<const float> ext_params = {});

  std::string device_description() const;
  bool is_cpu_device() const;  // lavapipe

 private:
  VulkanFieldDevice() = default;
  std::unique_ptr<VulkanField> base_;
  std::unique_ptr<VulkanExtendedField> ext_;
  ExtEvaluator ext_eval_;
};

}  // namespace streetsim::field
