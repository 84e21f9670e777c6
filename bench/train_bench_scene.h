// Scene setup shared by the training-step benches (train_bench, train_field_bench): the
// "WxHxN" setting, the KITTI-like pinhole on the synthetic street, and a target rendered from
// 0.3 m aside (so that gradients are non-trivial) with sparse depth samples.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/gaussians/synthetic_street.h"
#include "scene/train/losses.h"

namespace streetsim::bench {

struct BenchSetting {
  int width = 0, height = 0;
  size_t num_gaussians = 0;
};

// False for a malformed setting.
inline bool ParseBenchSetting(const std::string& s, BenchSetting* out) {
  std::vector<std::string> p = absl::StrSplit(s, 'x');
  return p.size() == 3 && absl::SimpleAtoi(p[0], &out->width) && absl::SimpleAtoi(p[1], &out->height) &&
         absl::SimpleAtoi(p[2], &out->num_gaussians);
}

inline PinholeCamera BenchCamera(int w, int h) {
  PinholeCamera cam;
  cam.width = w;
  cam.height = h;
  cam.fx = cam.fy = 721.5377 * w / 1242.0;
  cam.cx = (w - 1) / 2.0;
  cam.cy = (h - 1) / 2.0;
  cam.T_world_from_cam = StreetCameraPose(10.0);
  return cam;
}

struct BenchTarget {
  std::vector<float> rgb;
  std::vector<train::DepthSample> lidar;
};

inline BenchTarget RenderBenchTarget(Engine& engine, const GaussianStore& street, const PinholeCamera& cam) {
  BenchTarget t;
  auto sc = engine.Upload(street);
  RenderOutput o;
  PinholeCamera c2 = cam;
  c2.T_world_from_cam = StreetCameraPose(10.0, 0.3);
  (void)engine.Render(**sc, c2, {}, &o);
  t.rgb = o.rgb;
  for (size_t i = 0; i < o.depth.size(); i += 97)
    if (o.alpha[i] > 0.5f) t.lidar.push_back({static_cast<uint32_t>(i), o.depth[i] / o.alpha[i]});
  return t;
}

// The training loss of the benches: L1 + D-SSIM on the colour and the depth loss on the sparse
// samples, their gradients into d_rgb / d_depth (sized here).
inline void BenchLoss(ThreadPool& pool, const RenderOutput& out, const BenchTarget& target, int w, int h,
                      std::vector<float>* d_rgb, std::vector<float>* d_depth) {
  const size_t pixels = static_cast<size_t>(w) * h;
  d_rgb->assign(pixels * 3, 0.0f);
  d_depth->assign(pixels, 0.0f);
  train::L1Loss(pool, out.rgb.data(), target.rgb.data(), pixels * 3, 1.0f, d_rgb->data());
  train::Ssim(pool, out.rgb.data(), target.rgb.data(), w, h, -0.2f, d_rgb->data());
  train::DepthLoss(out.depth.data(), target.lidar, 0.5f, d_depth->data());
}

}  // namespace streetsim::bench
