// Stages a + b: per-Gaussian projection (shaders/project.comp mirrors
// render/common/projection_math.h), the visibility scan and the compaction of visible ids in
// index order with their depth keys.
#include <Eigen/Geometry>

#include <cstring>

#include "render/vulkan/stages.h"

namespace streetsim::vulkan {

absl::Status UploadGaussianGeometry(const Context& ctx, const Buffer& gauss, const GaussianStore& store) {
  return UploadWith(ctx, gauss, store.size() * 48, 48, [&](size_t begin, size_t end, std::byte* out) {
    float* dst = reinterpret_cast<float*>(out);
    for (size_t i = begin / 48; i < end / 48; ++i, dst += 12) {
      std::memcpy(dst, &store.means[i * 3], 12);
      dst[3] = store.opacity_logits[i];
      std::memcpy(dst + 4, &store.log_scales[i * 3], 12);
      dst[7] = 0.0f;
      std::memcpy(dst + 8, &store.rotations[i * 4], 16);
    }
  });
}

// Same float camera as the cpu backend (render/cpu/project.cc: MakeCameraParams): pose inverted in
// double, then rounded once.
ProjectPush MakeProjectPush(const PinholeCamera& camera, uint32_t n, int sh_degree) {
  ProjectPush p{};
  const Eigen::Isometry3d T_cam_from_world = camera.T_world_from_cam.inverse();
  const Eigen::Matrix3d R = T_cam_from_world.linear();
  const Eigen::Vector3d t = T_cam_from_world.translation();
  const Eigen::Vector3d c = camera.T_world_from_cam.translation();
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) p.R[r * 3 + k] = static_cast<float>(R(r, k));
    p.t[r] = static_cast<float>(t[r]);
    p.c[r] = static_cast<float>(c[r]);
  }
  p.fx = static_cast<float>(camera.fx);
  p.fy = static_cast<float>(camera.fy);
  p.cx = static_cast<float>(camera.cx);
  p.cy = static_cast<float>(camera.cy);
  p.width = camera.width;
  p.height = camera.height;
  p.tiles_x = (camera.width + kTileSize - 1) / kTileSize;
  p.tiles_y = (camera.height + kTileSize - 1) / kTileSize;
  p.n = n;
  p.sh_degree = sh_degree;
  return p;
}

void RecordProjectAndCompact(Recorder& rec, const Kernels& k, const ScanScratch& scratch,
                             const SceneBuffers& scene, const Buffer& counts, const Buffer& args,
                             const ProjectPush& push) {
  const Grid per_gaussian = GridFor(DivUp(push.n, kWorkgroupSize));
  rec.Dispatch(*k.project,
               {scene.gauss, scene.sh[0], scene.sh[1], scene.sh[2], scene.sh[3], scene.splats,
                scene.rects, scene.flags, scene.touched},
               push, per_gaussian);
  rec.Barrier();
  RecordScan(rec, k, scratch, *scene.flags, counts, kCountN, push.n, kCountV, /*saturate=*/false,
             Launch{nullptr, 0, push.n});
  rec.Dispatch(
      *k.compact,
      {scene.flags, scene.touched, scene.splats, scene.depth_keys[0], scene.ids[0], &counts},
      per_gaussian);
  // setup_args writes other elements of `counts` than compact reads, but in the same buffer.
  rec.Barrier();
  struct SetupPush {
    uint32_t mode;
    uint32_t instance_capacity;
  };
  rec.Dispatch(*k.setup_args, {&counts, &args}, SetupPush{0, 0}, Grid{1, 1});
  rec.Barrier();
}

}  // namespace streetsim::vulkan
