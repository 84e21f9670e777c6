// VulkanField's state (buffers, pipelines, per-batch recording helpers), shared by its two source
// files: vulkan_field.cc (forward, backward) and vulkan_field_optimizer.cc (the plane regularisers
// and Adam on the device). Private to render/vulkan/field.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "render/vulkan/buffer.h"
#include "render/vulkan/context.h"
#include "render/vulkan/pipeline.h"
#include "render/vulkan/field/field_device_util.h"
#include "render/vulkan/field/field_linear_push.h"
#include "render/vulkan/field/vulkan_field.h"

namespace streetsim::field {

namespace vulkan_field_internal {

namespace vk = vulkan;

constexpr int kMaxBindings = 12;         // field_sample_backward.glsl
constexpr uint32_t kWg = 256;            // field_common.glsl: FIELD_WG
constexpr uint32_t kGaussiansPerBackwardWg = 8;  // field_sample_backward.glsl: 256 / LANES
constexpr uint32_t kTile = 64;           // field_linear*.comp: 64 x 64 tiles
constexpr size_t kMinRowsPerChunk = 1024;  // field_linear_grad.comp: rows per partial sum
using vkgemm::kAccum, vkgemm::kBias, vkgemm::kMask, vkgemm::kReluOut, vkgemm::kTrans;  // field_linear.comp flags

struct SamplePush {
  float ax, ay, az, bx, by, bz, time_coord;
  uint32_t rows, time_res;
};
// field_linear*.comp and field_reduce.comp (shared with nn/vk_nn_kernels.cc): dense views here.
using vkgemm::GradPush;
using vkgemm::LinearPush;
using vkgemm::ReducePush;

inline uint32_t DivUp(uint64_t a, uint64_t b) { return static_cast<uint32_t>((a + b - 1) / b); }

inline absl::Status MakeBuffer(const vk::Context& ctx, vk::Buffer* out, size_t bytes, vk::Buffer::Kind kind,
                        const std::string& name) {
  auto b = vk::Buffer::Create(ctx, bytes, kind, name);
  if (!b.ok()) return b.status();
  *out = *std::move(b);
  return absl::OkStatus();
}

inline absl::Status CheckLayout(const FieldLayout& L) {
  if (L.channels < 1 || L.num_levels < 1 || L.width < 1 ||
      L.planes.size() != static_cast<size_t>(L.num_levels) * kPlanesPerLevel ||
      L.level_resolution.size() != static_cast<size_t>(L.num_levels) || L.time_resolution < 2 ||
      L.total <= L.grid_size) {
    return absl::InvalidArgumentError("vulkan field: malformed FieldLayout (use FieldLayout::Make)");
  }
  for (int r : L.level_resolution) {
    if (r < 2) return absl::InvalidArgumentError("vulkan field: spatial resolution < 2");
  }
  return absl::OkStatus();
}

}  // namespace vulkan_field_internal

// This header is private to VulkanField's two source files, which use these helpers unqualified.
using namespace vulkan_field_internal;  // NOLINT(build/namespaces)
namespace vk = vulkan;

struct VulkanField::Impl {
  // Declared first: destroyed last, after every buffer and pipeline of its device.
  std::unique_ptr<vk::Context> ctx;
  FieldLayout layout;
  VulkanFieldOptions options;
  std::unique_ptr<vk::ComputePipeline> sample, linear, linear_grad, reduce, sample_backward;
  bool float_atomics = false;

  // Plane groups: group g holds the flat parameters [group_begin[g], group_end[g]).
  std::vector<size_t> group_begin, group_end;
  std::vector<vk::Buffer> planes, grads;
  vk::Buffer plane_table, mlp, d_mlp;
  size_t mlp_total = 0;

  // Per-batch buffers (backward ones made on first use).
  size_t batch = 0, rows_per_chunk = 0, chunks = 0;
  vk::Buffer means, features, act, pos_hidden, sh_hidden, dx, dsh;
  vk::Buffer g_dx, g_dsh, d_pos_hidden, d_sh_hidden, d_act, d_features, d_means, partials;
  vk::Buffer staging, readback, grad_readback;

  // The optimiser on the device (vulkan_field_optimizer.cc; made at its first use): Adam's
  // moments per plane group and for the MLP, the regularisers' per-workgroup loss sums.
  std::unique_ptr<vk::ComputePipeline> plane_reg, adam;
  std::vector<vk::Buffer> m_planes, v_planes;
  vk::Buffer m_mlp, v_mlp, reg_partials, reg_readback;

  FieldFrame frame;  // after the buffers: its destructor waits for the device first
  VulkanFieldTimings last_forward, last_backward;

  const vk::Buffer* PlaneBuf(int g) const { return &planes[std::min<int>(g, planes.size() - 1)]; }
  const vk::Buffer* GradBuf(int g) const { return &grads[std::min<int>(g, grads.size() - 1)]; }
  uint32_t MlpOffset(size_t flat) const { return static_cast<uint32_t>(flat - layout.grid_size); }

  absl::Status Init(std::span<const float> params);
  absl::Status Upload(std::span<const float> params);
  absl::Status EnsureBackwardBuffers();
  // VulkanField::Backward (d_params: the host array the gradient is added into) and
  // BackwardOnDevice (d_params empty: the gradient stays in `grads` and `d_mlp`).
  absl::Status Backward(const FieldQuery& query, std::span<const float> means, std::span<const float> d_dx,
                        std::span<const float> d_dsh, std::span<float> d_params, std::span<float> d_means);
  // One device buffer per plane group, sized as the group, named "`name` g".
  absl::Status MakeGroupBuffers(std::vector<vk::Buffer>* out, const std::string& name) const {
    out->clear();
    for (size_t g = 0; g < group_begin.size(); ++g) {
      out->emplace_back();
      if (auto s = MakeBuffer(*ctx, &out->back(), (group_end[g] - group_begin[g]) * sizeof(float),
                              vk::Buffer::Kind::kDevice, absl::StrCat(name, " ", g));
          !s.ok()) {
        return s;
      }
    }
    return absl::OkStatus();
  }
  absl::Status ZeroGradients();    // vulkan_field_optimizer.cc
  absl::Status EnsureOptimizer();  // vulkan_field_optimizer.cc
  absl::Status MakeOptimizer();    // EnsureOptimizer's work (it clears what a failure left)
  SamplePush MakeSamplePush(const FieldQuery& q, size_t rows) const;

  void Linear(vk::Recorder& rec, const vk::Buffer& x, const vk::Buffer& y, const vk::Buffer* mask, uint32_t rows,
              uint32_t K, uint32_t N, const DenseInfo& d, uint32_t flags) const {
    const LinearPush push{rows, K, N, MlpOffset(d.w_offset), MlpOffset(d.b_offset), flags, 0, K, 0, N};
    rec.Dispatch(*linear, {&x, &mlp, &y, mask ? mask : &y}, push,
                 vk::GridFor(uint64_t{DivUp(rows, kTile)} * DivUp(N, kTile)));
  }
  // The activations are stored after their ReLU, so the input needs none (relu_in 0).
  void LinearGrad(vk::Recorder& rec, const vk::Buffer& dy, const vk::Buffer& x, uint32_t rows,
                  const DenseInfo& d) const {
    const GradPush push{rows, static_cast<uint32_t>(d.out), static_cast<uint32_t>(d.in),
                        static_cast<uint32_t>(rows_per_chunk), MlpOffset(d.w_offset), MlpOffset(d.b_offset),
                        static_cast<uint32_t>(mlp_total), 0u, 0u, static_cast<uint32_t>(d.out), 0u,
                        static_cast<uint32_t>(d.in)};
    const uint64_t groups = uint64_t{DivUp(rows, rows_per_chunk)} * DivUp(d.out, kTile) * DivUp(d.in + 1, kTile);
    rec.Dispatch(*linear_grad, {&dy, &x, &partials}, push, vk::GridFor(groups));
  }
  void Sample(vk::Recorder& rec, const SamplePush& push) const {
    rec.Dispatch(*sample, {PlaneBuf(0), PlaneBuf(1), PlaneBuf(2), PlaneBuf(3), &plane_table, &means, &features},
                 push, vk::GridFor(DivUp(uint64_t{push.rows} * layout.feature_dim(), kWg)));
  }
  // The forward up to the heads' hidden layers (Forward, and Backward's recomputation): sample the
  // planes at the `rows` means, the trunk, then the first layer of the heads asked for.
  void RecordHidden(vk::Recorder& rec, const FieldQuery& query, size_t rows, bool pos_head, bool sh_head) const {
    const uint32_t r = static_cast<uint32_t>(rows), D = layout.feature_dim(), W = layout.width;
    Sample(rec, MakeSamplePush(query, rows));
    rec.Barrier();
    Linear(rec, features, act, nullptr, r, D, W, layout.trunk, kBias | kReluOut);
    rec.Barrier();
    if (pos_head) Linear(rec, act, pos_hidden, nullptr, r, W, W, layout.pos1, kBias | kReluOut);
    if (sh_head) Linear(rec, act, sh_hidden, nullptr, r, W, W, layout.sh1, kBias | kReluOut);
  }
};

}  // namespace streetsim::field
