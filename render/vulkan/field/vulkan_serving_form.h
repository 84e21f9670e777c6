// The serving form (scene/field/serving_form.h) evaluated by a compute kernel straight into a
// Vulkan engine's copy of the scene (docs/field.md "Serving form", "On a Vulkan engine"): the
// form's tables live on the engine's device, and a new time is one dispatch per table buffer
// that writes the moving Gaussians' modelled values in the scene's own buffers. Nothing crosses
// the bus per step but the push constants; the host's copy (what the LiDAR renders) is evaluated
// only when asked for.
//
// The tables are uploaded once (FormTables::RecordLayout's records, about 240 B per moving
// Gaussian for S3Gaussian's field), split over buffers within the device's storage-buffer range.
// Not thread-safe: one caller at a time (the server calls it under its engine lock).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/field/serving_form.h"

namespace streetsim::field {

class VulkanServingForm : public DeviceSceneWriter {
 public:
  // FailedPrecondition when `engine` is not a Vulkan engine; InvalidArgument for a form without
  // SH degree 3 Gaussians. `form` must outlive nothing: its tables are copied to the device.
  // max_buffer_bytes (0: the device's maxStorageBufferRange) caps each table buffer; tests set
  // it small to split a small form over several.
  static absl::StatusOr<std::unique_ptr<VulkanServingForm>> Create(Engine& engine, const ServingForm& form,
                                                                    size_t max_buffer_bytes = 0);
  ~VulkanServingForm() override;
  VulkanServingForm(const VulkanServingForm&) = delete;
  VulkanServingForm& operator=(const VulkanServingForm&) = delete;

  // Writes the form at `time_us` (clamped to its time range) into `scene`: a scene of this
  // engine holding the form's Gaussians at any time (rows the form does not change keep their
  // values, as ServingForm::At leaves them).
  absl::Status WriteAt(int64_t time_us, DeviceScene* scene) override;
  std::string device() const override;  // "vulkan" (kVulkanServingDevice)

  size_t device_bytes() const;  // the tables on the device
  int table_buffers() const;
  std::string device_description() const;

  struct Impl;

 private:
  explicit VulkanServingForm(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace streetsim::field
