// The extended field's HexPlane token features on Vulkan (internal to VulkanExtendedField; the cpu
// reference is scene/field/extended/extended_sampling.h): per Gaussian the spatial product S(x)
// once and f(x, t_j) = S(x) ⊙ T(x, t_j) for the K token times (shaders/ext_sample.comp), and the
// backward (shaders/ext_sample_backward.glsl): plane-texel gradients scattered with float atomics
// (else a compare-and-swap loop) into device gradient buffers grouped as the planes, dL/d(means)
// through the sampling coordinates. Owns the planes (packed as VulkanField's: plane_groups.h);
// records into the caller's command buffer, never submits except in the explicit transfers.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "scene/field/deformation_field.h"
#include "render/vulkan/field/plane_groups.h"

namespace streetsim::field {

inline constexpr int kVkMaxTokens = 9;  // ext_common.glsl: MAX_TOKENS

class VkTokenSampler {
 public:
  // `ctx` must outlive the sampler. dilation > 0: also S_dil, the VAE variance branch's input
  // (extended_config.h). max_plane_buffer_bytes 0: the device's range.
  static absl::StatusOr<std::unique_ptr<VkTokenSampler>> Create(const vulkan::Context& ctx, const FieldLayout& layout,
                                                                int tokens, int dilation,
                                                                size_t max_plane_buffer_bytes, bool force_cas_atomics);
  ~VkTokenSampler();

  // The planes of `base_params` (FieldLayout order, layout.total floats).
  absl::Status UploadPlanes(std::span<const float> base_params);

  // The pass's normaliser and token times, as TokenSampler's constructor (double, rounded once).
  void SetPass(const FieldAabb& aabb, double time_coord, double dt);
  const float* nm_a() const { return nm_a_; }
  const float* nm_b() const { return nm_b_; }
  const float* token_times() const { return token_time_; }

  // Where S(x) goes / dL/dS comes from: element (g, d) at base + g * stride + d of `buffer`
  // (stride 0: nowhere / zero). Forward only: the row's `geom_cols` values of `geom` ([rows x
  // geom_cols]) are copied to columns [0, geom_cols) of the same row first (the encoder's input).
  struct SView {
    const vulkan::Buffer* buffer = nullptr;
    uint32_t base = 0, stride = 0;
    const vulkan::Buffer* geom = nullptr;
    uint32_t geom_cols = 0;
  };
  // ftok [rows x K*D] (written); with a dilation s_dil [rows x D] (written).
  void RecordForward(vulkan::Recorder& rec, uint32_t rows, const vulkan::Buffer& means, const SView& s,
                     const vulkan::Buffer& ftok, const vulkan::Buffer* s_dil) const;
  // Plane gradients added to the device gradient buffers; d_means [rows x 3] written; d_sdil
  // [rows x D]: dL/dS_dil (with a dilation).
  void RecordBackward(vulkan::Recorder& rec, uint32_t rows, const vulkan::Buffer& means, const SView& d_s,
                      const vulkan::Buffer& d_ftok, const vulkan::Buffer* d_sdil, const vulkan::Buffer& d_means) const;
  void RecordZeroGrads(vulkan::Recorder& rec) const;
  // Adds the device plane gradients into d_base (FieldLayout order) through `readback` (a
  // kReadback buffer, grown as needed).
  absl::Status DownloadAddGrads(vulkan::Buffer* readback, float* d_base) const;

  bool uses_float_atomics() const { return float_atomics_; }
  int plane_buffers() const { return static_cast<int>(planes_.size()); }
  int tokens() const { return K_; }

 private:
  VkTokenSampler(const vulkan::Context& ctx, const FieldLayout& layout, int tokens, int dilation)
      : ctx_(ctx), layout_(layout), K_(tokens), dilation_(dilation) {}
  const vulkan::Buffer* PlaneBuf(size_t g) const { return &planes_[std::min(g, planes_.size() - 1)]; }
  const vulkan::Buffer* GradBuf(size_t g) const { return &grads_[std::min(g, grads_.size() - 1)]; }

  const vulkan::Context& ctx_;
  FieldLayout layout_;
  int K_;
  int dilation_;
  bool float_atomics_ = false;
  PlaneGroups groups_;
  std::vector<vulkan::Buffer> planes_, grads_;
  vulkan::Buffer table_;
  std::unique_ptr<vulkan::ComputePipeline> forward_, backward_;
  float nm_a_[3] = {0, 0, 0}, nm_b_[3] = {0, 0, 0};
  float token_time_[kVkMaxTokens] = {};
};

}  // namespace streetsim::field
