// The served scenes' field on a Vulkan device (the server's --field-device, docs/server.md
// "Field device"): ServingField (S3Gaussian's field) and ExtServingField (the extended field,
// inference z = μ) evaluate their dynamic Gaussians on a VulkanFieldDevice (the trainer's too); the static skip, the baked Gaussians and the deformed store on the host are unchanged.
//
// The device field is created on the scene's first evaluation with a dynamic Gaussian (a scene
// whose Gaussians are all static never touches the device), is owned by the scene and released
// with it. Creation or evaluation errors (no device, device lost, out of memory) move the scene
// to the cpu for good with a warning (ServedScene::DeviceFailed): the request is answered.
#pragma once

#include "scene/field/extended/extended_serving.h"
#include "scene/field/static_skip.h"
#include "render/engine.h"
#include "render/vulkan/field/vulkan_field.h"

namespace streetsim::field {

inline constexpr char kVulkanServingDevice[] = "vulkan";  // ServedScene::device() while on Vulkan

// The device hooks, for ServingField::Create / ExtServingField::Create (the static analysis runs
// there too). VulkanFieldOptions::device picks the device (kGpu: a GPU, else lavapipe).
ServingField::Device VulkanFieldForward(const VulkanFieldOptions& options = {});
ExtServingField::Device VulkanExtFieldForward(const VulkanFieldOptions& options = {});

// The served scene written by `engine`'s own device where it can be: a serving form on a Vulkan
// engine (VulkanServingForm, its tables uploaded now); nullptr otherwise (the host evaluates and
// the engine uploads what changed). Errors are the device's (creation, upload).
absl::StatusOr<std::unique_ptr<DeviceSceneWriter>> DeviceWriterFor(Engine& engine, const ServedScene& served);

// The same hooks on a scene already created (its analysis stays as it was made).
void ServeOnVulkan(ServingField& scene, const VulkanFieldOptions& options = {});
void ServeOnVulkan(ExtServingField& scene, const VulkanFieldOptions& options = {});

}  // namespace streetsim::field
