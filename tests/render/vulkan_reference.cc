#include "tests/render/vulkan_reference.h"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <numeric>
#include <random>

#include "render/common/projection_math.h"

namespace streetsim::testing {

ReferenceImage RenderReference(const GaussianStore& store, const PinholeCamera& camera,
                               const Eigen::Vector3f& background) {
  projection::CameraParams<float> cam{};
  const Eigen::Isometry3d T_cam_from_world = camera.T_world_from_cam.inverse();
  const Eigen::Matrix3d R = T_cam_from_world.linear();
  const Eigen::Vector3d t = T_cam_from_world.translation();
  const Eigen::Vector3d c = camera.T_world_from_cam.translation();
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) cam.R_cam_from_world[r * 3 + k] = static_cast<float>(R(r, k));
    cam.t_cam_from_world[r] = static_cast<float>(t[r]);
    cam.cam_center_world[r] = static_cast<float>(c[r]);
  }
  cam.fx = static_cast<float>(camera.fx);
  cam.fy = static_cast<float>(camera.fy);
  cam.cx = static_cast<float>(camera.cx);
  cam.cy = static_cast<float>(camera.cy);
  cam.width = camera.width;
  cam.height = camera.height;
  cam.tiles_x = (camera.width + 15) / 16;
  cam.tiles_y = (camera.height + 15) / 16;

  const size_t n = store.size();
  const int K = store.sh_coeffs();
  std::vector<projection::Splat<float>> splats(n);
  std::vector<projection::TileRect> rects(n);
  std::vector<uint32_t> visible;
  for (size_t i = 0; i < n; ++i) {
    float band = 0;
    if (projection::ProjectGaussian<float>(cam, &store.means[i * 3], &store.log_scales[i * 3],
                                           &store.rotations[i * 4], store.opacity_logits[i],
                                           &store.sh[i * K * 3], store.sh_degree, &splats[i],
                                           &rects[i], &band)) {
      visible.push_back(static_cast<uint32_t>(i));
    }
  }
  std::stable_sort(visible.begin(), visible.end(),
                   [&](uint32_t a, uint32_t b) { return splats[a].depth < splats[b].depth; });
  std::vector<std::vector<uint32_t>> tiles(static_cast<size_t>(cam.tiles_x) * cam.tiles_y);
  ReferenceImage img;
  img.width = camera.width;
  img.height = camera.height;
  img.num_visible = visible.size();
  for (uint32_t id : visible) {
    const projection::TileRect& r = rects[id];
    for (int ty = r.y0; ty < r.y1; ++ty) {
      for (int tx = r.x0; tx < r.x1; ++tx) {
        tiles[static_cast<size_t>(ty) * cam.tiles_x + tx].push_back(id);
        ++img.num_tile_instances;
      }
    }
  }

  const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
  img.rgb.resize(pixels * 3);
  img.depth.resize(pixels);
  img.alpha.resize(pixels);
  img.final_t.resize(pixels);
  img.n_contrib.resize(pixels);
  for (int v = 0; v < camera.height; ++v) {
    for (int u = 0; u < camera.width; ++u) {
      const auto& list = tiles[static_cast<size_t>(v / 16) * cam.tiles_x + u / 16];
      float T = 1, C[3] = {0, 0, 0}, D = 0;
      uint32_t last = 0;
      for (size_t j = 0; j < list.size(); ++j) {
        const projection::Splat<float>& s = splats[list[j]];
        const float dx = s.x - static_cast<float>(u), dy = s.y - static_cast<float>(v);
        const float power =
            -0.5f * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) - s.conic[1] * dx * dy;
        if (power > 0) continue;
        const float alpha = std::min(0.99f, s.opacity * std::exp(power));
        if (alpha < 1.0f / 255.0f) continue;
        const float test_T = T * (1 - alpha);
        if (test_T < 1e-4f) break;
        const float w = alpha * T;
        for (int ch = 0; ch < 3; ++ch) C[ch] += w * s.rgb[ch];
        D += w * s.depth;
        T = test_T;
        last = static_cast<uint32_t>(j + 1);
      }
      const size_t pix = static_cast<size_t>(v) * camera.width + u;
      for (int ch = 0; ch < 3; ++ch) img.rgb[pix * 3 + ch] = C[ch] + T * background[ch];
      img.depth[pix] = D;
      img.alpha[pix] = 1 - T;
      img.final_t[pix] = T;
      img.n_contrib[pix] = last;
    }
  }
  return img;
}

GaussianStore MakeRandomScene(const SceneOptions& options) {
  std::mt19937 rng(options.seed);
  auto uni = [&](float a, float b) { return std::uniform_real_distribution<float>(a, b)(rng); };
  GaussianStore store;
  store.sh_degree = options.sh_degree;
  store.Resize(options.num_gaussians);
  const int K = store.sh_coeffs();
  for (int i = 0; i < options.num_gaussians; ++i) {
    float z = uni(1.0f, 30.0f);
    float x = uni(-0.6f, 0.6f) * z, y = uni(-0.4f, 0.4f) * z;
    float log_s[3] = {std::log(uni(0.02f, 0.6f)), std::log(uni(0.02f, 0.6f)),
                      std::log(uni(0.02f, 0.6f))};
    float logit = uni(-3.0f, 4.0f);
    if (options.hard_cases) {
      switch (i % 11) {
        case 1:
          z = uni(-5.0f, 0.19f);
          break;  // behind / at the near plane
        case 2:
          z = uni(0.15f, 0.6f);
          x *= 0.05f;
          y *= 0.05f;
          break;  // across the near plane
        case 3:
          for (float& s : log_s) s = std::log(uni(3.0f, 20.0f));
          break;  // huge
        case 4:
          for (float& s : log_s) s = std::log(uni(1e-4f, 3e-3f));
          break;  // tiny
        case 5:
          logit = uni(-9.0f, -5.0f);
          break;  // nearly transparent
        case 6:
          x = uni(-3.0f, 3.0f) * z;
          break;  // far outside the frustum
        case 7:
          log_s[0] = std::log(2.0f);
          log_s[1] = std::log(0.005f);
          break;  // needle
        default:
          break;
      }
    }
    store.means[i * 3 + 0] = x;
    store.means[i * 3 + 1] = y;
    store.means[i * 3 + 2] = z;
    for (int k = 0; k < 3; ++k) store.log_scales[i * 3 + k] = log_s[k];
    for (int k = 0; k < 4; ++k) store.rotations[i * 4 + k] = uni(-1.0f, 1.0f);
    store.rotations[i * 4] += 1.5f;  // never all zero
    store.opacity_logits[i] = logit;
    for (int k = 0; k < K; ++k) {
      for (int ch = 0; ch < 3; ++ch) {
        store.sh[(static_cast<size_t>(i) * K + k) * 3 + ch] =
            k == 0 ? uni(-1.5f, 1.5f) : uni(-0.4f, 0.4f);
      }
    }
  }
  return store;
}

PinholeCamera MakeCamera(int width, int height, double focal_px, double cx_offset_px,
                         double cy_offset_px) {
  PinholeCamera cam;
  cam.width = width;
  cam.height = height;
  cam.fx = focal_px;
  cam.fy = focal_px * 1.02;
  cam.cx = (width - 1) / 2.0 + cx_offset_px;
  cam.cy = (height - 1) / 2.0 + cy_offset_px;
  return cam;
}

}  // namespace streetsim::testing
