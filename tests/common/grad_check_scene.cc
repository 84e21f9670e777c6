#include "tests/common/grad_check_scene.h"

#include <cmath>
#include <random>

#include "render/cpu/binning.h"
#include "render/cpu/blend.h"
#include "render/cpu/project.h"

namespace streetsim::gradcheck {

Scene RandomScene(unsigned seed, int n, int degree, int width, int height) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0, 1);
  Scene s;
  s.cam.width = width;
  s.cam.height = height;
  s.cam.fx = 60;
  s.cam.fy = 64;
  s.cam.cx = width * 0.47;
  s.cam.cy = height * 0.53;
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() = Eigen::AngleAxisd(0.1, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
  pose.translation() = Eigen::Vector3d(0.2, -0.1, -0.3);
  s.cam.T_world_from_cam = pose;
  s.background = Eigen::Vector3f(0.2f, 0.5f, 0.1f);
  GaussianStore& g = s.store;
  g.sh_degree = degree;
  g.Resize(n);
  const int K = g.sh_coeffs();
  for (int i = 0; i < n; ++i) {
    const double z = 2.5 + 3.0 * u(rng);
    const Eigen::Vector3d p_cam((u(rng) - 0.5) * 1.1 * z * width / s.cam.fx, (u(rng) - 0.5) * 1.1 * z * height / s.cam.fy, z);
    const Eigen::Vector3d p = pose * p_cam;
    for (int k = 0; k < 3; ++k) {
      g.means[i * 3 + k] = static_cast<float>(p[k]);
      g.log_scales[i * 3 + k] = std::log(0.04f + 0.12f * u(rng));
    }
    for (int k = 0; k < 4; ++k) g.rotations[i * 4 + k] = u(rng) - 0.5f + (k == 0 ? 0.6f : 0.0f);
    g.opacity_logits[i] = -1.5f + 2.5f * u(rng);  // opacity 0.18..0.73: below the 0.99 clamp
    for (int k = 0; k < K * 3; ++k) g.sh[i * K * 3 + k] = (k < 3 ? 1.2f : 0.35f) * (u(rng) - 0.5f);
  }
  const size_t pix = static_cast<size_t>(width) * height;
  for (size_t i = 0; i < pix * 3; ++i) s.w_rgb.push_back(u(rng) - 0.3);
  for (size_t i = 0; i < pix; ++i) s.w_depth.push_back(0.1 * (u(rng) - 0.5));
  for (size_t i = 0; i < pix; ++i) s.w_alpha.push_back(u(rng) - 0.5);
  return s;
}

double LossDouble(ThreadPool& pool, const Scene& s, const GaussianStore& store) {
  cpu::Frame<double> f;
  const auto cam = cpu::MakeCameraParams<double>(s.cam);
  f.width = s.cam.width;
  f.height = s.cam.height;
  f.tiles_x = cam.tiles_x;
  f.tiles_y = cam.tiles_y;
  cpu::ProjectGaussians<double>(pool, store, cam, &f);
  cpu::SortByDepth(&f);
  cpu::BinTiles(pool, &f);
  const size_t pix = static_cast<size_t>(f.width) * f.height;
  std::vector<double> rgb(pix * 3), depth(pix), alpha(pix);
  cpu::BlendArgs<double> args;
  args.frame = &f;
  for (int c = 0; c < 3; ++c) args.background[c] = s.background[c];
  args.rgb = rgb.data();
  args.depth = depth.data();
  args.alpha = alpha.data();
  cpu::BlendScalar<double>(pool, args);
  double loss = 0;
  for (size_t i = 0; i < pix * 3; ++i) loss += s.w_rgb[i] * rgb[i];
  for (size_t i = 0; i < pix; ++i) loss += s.w_depth[i] * depth[i] + s.w_alpha[i] * alpha[i];
  return loss;
}

}  // namespace streetsim::gradcheck
