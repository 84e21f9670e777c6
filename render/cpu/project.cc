#include "render/cpu/project.h"
#include "render/cpu/simd_dispatch.h"

#include <algorithm>

namespace streetsim::cpu {

template <typename Real>
projection::CameraParams<Real> MakeCameraParams(const PinholeCamera& camera) {
  projection::CameraParams<Real> p{};
  const Eigen::Isometry3d T_cam_from_world = camera.T_world_from_cam.inverse();
  const Eigen::Matrix3d R = T_cam_from_world.linear();
  const Eigen::Vector3d t = T_cam_from_world.translation();
  const Eigen::Vector3d c = camera.T_world_from_cam.translation();
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) p.R_cam_from_world[r * 3 + k] = static_cast<Real>(R(r, k));
    p.t_cam_from_world[r] = static_cast<Real>(t[r]);
    p.cam_center_world[r] = static_cast<Real>(c[r]);
  }
  p.fx = static_cast<Real>(camera.fx);
  p.fy = static_cast<Real>(camera.fy);
  p.cx = static_cast<Real>(camera.cx);
  p.cy = static_cast<Real>(camera.cy);
  p.width = camera.width;
  p.height = camera.height;
  p.tiles_x = (camera.width + 15) / 16;
  p.tiles_y = (camera.height + 15) / 16;
  return p;
}

namespace {
// Visible ids in index order: the order the depth sort breaks ties by, on every backend.
template <typename Real>
void CollectVisible(Frame<Real>* frame) {
  frame->visible_ids.clear();
  for (size_t i = 0; i < frame->visible.size(); ++i) {
    if (frame->visible[i]) frame->visible_ids.push_back(static_cast<uint32_t>(i));
  }
}
}  // namespace

template <typename Real>
void ProjectGaussians(ThreadPool& pool, const GaussianStore& store,
                      const projection::CameraParams<Real>& cam, Frame<Real>* frame) {
  const size_t n = store.size();
  frame->splats.resize(n);
  frame->rects.resize(n);
  frame->visible.resize(n);
  const int degree = store.sh_degree;
  const int K = store.sh_coeffs();

  pool.ParallelFor(static_cast<int64_t>(n), 2048, [&](int64_t begin, int64_t end, int) {
    Real mean[3], log_scale[3], quat[4], sh[16 * 3];
    for (int64_t i = begin; i < end; ++i) {
      // float store -> Real working copies (a no-op for float, widening for the double reference).
      for (int k = 0; k < 3; ++k) {
        mean[k] = store.means[i * 3 + k];
        log_scale[k] = store.log_scales[i * 3 + k];
      }
      for (int k = 0; k < 4; ++k) quat[k] = store.rotations[i * 4 + k];
      const float* sh_src = &store.sh[static_cast<size_t>(i) * K * 3];
      for (int k = 0; k < K * 3; ++k) sh[k] = sh_src[k];

      projection::Splat<Real> sp;
      projection::TileRect rect{0, 0, 0, 0};
      Real band = 0;
      const bool vis = projection::ProjectGaussian<Real>(
          cam, mean, log_scale, quat, static_cast<Real>(store.opacity_logits[i]), sh, degree, &sp,
          &rect, &band);
      frame->visible[i] = vis;
      frame->rects[i] = vis ? rect : projection::TileRect{0, 0, 0, 0};
      if (vis) {
        BlendSplat<Real>& b = frame->splats[i];
        b.x = sp.x;
        b.y = sp.y;
        b.a = sp.conic[0];
        b.b = sp.conic[1];
        b.c = sp.conic[2];
        b.opacity = sp.opacity;
        b.r = sp.rgb[0];
        b.g = sp.rgb[1];
        b.bl = sp.rgb[2];
        b.depth = sp.depth;
        b.band = band;
        b.det_conic = sp.det_conic;
        b.reach2 = band * band * b.det_conic;  // band^2 = d2 * cov_yy and cov_yy = a / det_conic
        b.b_over_a = b.b / b.a;
        b.inv_a = Real(1) / b.a;
        b.pad = 0;
      }
    }
  });

  CollectVisible(frame);
}

void ProjectGaussiansSimd(ThreadPool& pool, const SceneSoa& scene,
                          const projection::CameraParams<float>& cam, Frame<float>* frame) {
  frame->splats.resize(scene.n);
  frame->rects.resize(scene.n);
  frame->visible.resize(scene.n);
  static const auto range_fn = PickSimd(&project_avx2::ProjectRange, &project_avx512::ProjectRange);
  pool.ParallelFor(static_cast<int64_t>(scene.n), 4096, [&](int64_t begin, int64_t end, int) {
    range_fn(scene, cam, begin, end, frame);
  });
  CollectVisible(frame);
}

template projection::CameraParams<float> MakeCameraParams<float>(const PinholeCamera&);
template projection::CameraParams<double> MakeCameraParams<double>(const PinholeCamera&);
template void ProjectGaussians<float>(ThreadPool&, const GaussianStore&,
                                      const projection::CameraParams<float>&, Frame<float>*);
template void ProjectGaussians<double>(ThreadPool&, const GaussianStore&,
                                       const projection::CameraParams<double>&, Frame<double>*);

}  // namespace streetsim::cpu
