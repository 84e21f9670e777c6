#include "render/vulkan/param_upload.h"

#include <atomic>
#include <cstdint>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "render/vulkan/engine_impl.h"

namespace streetsim::vulkan {
namespace {
// 1 where the float is inf or nan (exponent all ones): an integer test,
// whatever the float flags.
inline uint32_t NonFinite(float v) {
  uint32_t b;
  std::memcpy(&b, &v, 4);
  return (b & 0x7f800000u) == 0x7f800000u;
}
} // namespace

ParamPackLayout MakeParamPackLayout(size_t n, int sh_coeffs) {
  ParamPackLayout l;
  l.n = n;
  l.sh_coeffs = sh_coeffs;
  l.geometry_bytes = n * 48;
  size_t offset = l.geometry_bytes;
  for (int g = 0; g < kMaxShGroups; ++g) {
    l.sh_offset[g] = offset;
    l.sh_bytes[g] = n * static_cast<size_t>(ShGroupFloats(sh_coeffs, g)) * 4;
    offset += l.sh_bytes[g];
  }
  l.total_bytes = offset;
  return l;
}

absl::Status PackParams(const GaussianParamsView &p,
                        const ParamPackLayout &layout, ThreadPool &pool,
                        std::byte *out) {
  const int K = layout.sh_coeffs;
  if (p.n != layout.n || p.sh_stride < K ||
      ShCoeffsForDegree(p.sh_degree) != K) {
    return absl::InvalidArgumentError(
        "vulkan: UpdateSceneParams: view does not match the scene layout");
  }
  std::atomic<int64_t> first_bad{-1};
  const size_t stride = static_cast<size_t>(p.sh_stride) * 3;
  pool.ParallelFor(
      static_cast<int64_t>(p.n), 4096, [&](int64_t i0, int64_t i1, int) {
        float *geo =
            reinterpret_cast<float *>(out) + static_cast<size_t>(i0) * 12;
        uint32_t bad = 0;
        for (int64_t i = i0; i < i1; ++i, geo += 12) {
          const float *m = p.means + i * 3;
          const float *ls = p.log_scales + i * 3;
          const float *q = p.rotations + i * 4;
          std::memcpy(geo, m, 12);
          geo[3] = p.opacity_logits[i];
          std::memcpy(geo + 4, ls, 12);
          geo[7] = 0.0f;
          std::memcpy(geo + 8, q, 16);
          for (int k = 0; k < 12; ++k)
            bad |= NonFinite(geo[k]);
          bad |= q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3] < 1e-20f;
        }
        for (int g = 0; g < kMaxShGroups; ++g) {
          const size_t floats =
              layout.sh_bytes[g] / 4 / std::max<size_t>(layout.n, 1);
          if (floats == 0)
            continue;
          float *dst = reinterpret_cast<float *>(out + layout.sh_offset[g]) +
                       static_cast<size_t>(i0) * floats;
          for (int64_t i = i0; i < i1; ++i, dst += floats) {
            std::memcpy(
                dst, p.sh + i * stride + static_cast<size_t>(g) * kShGroup * 3,
                floats * 4);
            for (size_t k = 0; k < floats; ++k)
              bad |= NonFinite(dst[k]);
          }
        }
        if (bad != 0) {
          int64_t expected = -1;
          first_bad.compare_exchange_strong(expected, i0);
        }
      });
  if (const int64_t b = first_bad.load(); b >= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("vulkan: UpdateSceneParams: non-finite parameter or zero "
                     "rotation among Gaussians from ",
                     b));
  }
  return absl::OkStatus();
}

absl::Status
VulkanEngine::UpdateSceneParams(const GaussianParamsView &params,
                                std::unique_ptr<DeviceScene> *scene) {
  auto *vscene =
      scene->get() ? dynamic_cast<VulkanScene *>(scene->get()) : nullptr;
  if (vscene == nullptr || vscene->engine_id() != id_ ||
      vscene->size() != params.n || vscene->sh_degree() != params.sh_degree ||
      params.n == 0) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (kept_.scene == vscene)
        kept_.scene = nullptr;
    }
    return Engine::UpdateSceneParams(params, scene);
  }
  std::lock_guard<std::mutex> lock(mu_);
  if (kept_.scene == vscene)
    kept_.scene = nullptr; // the kept splats no longer match
  const ParamPackLayout layout =
      MakeParamPackLayout(params.n, ShCoeffsForDegree(params.sh_degree));
  const Context &c = *ctx_;
  if (absl::Status s =
          EnsureBufferCapacity(c, &param_staging_, layout.total_bytes,
                               Buffer::Kind::kStaging, "param_staging");
      !s.ok()) {
    return s;
  }
  if (host_pool_ == nullptr)
    host_pool_ = std::make_unique<ThreadPool>(0);
  if (absl::Status s =
          PackParams(params, layout, *host_pool_,
                     static_cast<std::byte *>(param_staging_.mapped()));
      !s.ok()) {
    return s;
  }
  return c.SubmitAndWait([&](VkCommandBuffer cmd) {
    const VkBufferCopy geo{0, 0, layout.geometry_bytes};
    vkCmdCopyBuffer(cmd, param_staging_.handle(), vscene->gauss.handle(), 1,
                    &geo);
    for (int g = 0; g < kMaxShGroups; ++g) {
      if (layout.sh_bytes[g] == 0)
        continue;
      const VkBufferCopy region{layout.sh_offset[g], 0, layout.sh_bytes[g]};
      vkCmdCopyBuffer(cmd, param_staging_.handle(), vscene->sh[g].handle(), 1,
                      &region);
    }
  });
}

} // namespace streetsim::vulkan
