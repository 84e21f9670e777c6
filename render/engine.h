// The rendering engine interface: one interface, two backends (cpu, vulkan).
//
// A scene is uploaded once into the backend's own memory (host arrays for cpu, device buffers for
// vulkan) and then rendered from any number of cameras without per-frame copies of the Gaussians.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "render/camera.h"
#include "scene/gaussians/gaussian_store.h"

namespace streetsim {

enum class Backend { kAuto, kCpu, kVulkan };
absl::StatusOr<Backend> ParseBackend(std::string_view name);  // "auto" | "cpu" | "vulkan"
std::string_view BackendName(Backend backend);

// Constants of the 3DGS forward pass that both backends share (kept together so they agree).
struct RasterConstants {
  static constexpr int kTileSize = 16;
  static constexpr float kNearPlaneM = 0.2f;       // cull Gaussians with camera z <= this
  static constexpr float kLowPassPx = 0.3f;        // added to the 2D covariance diagonal
  static constexpr float kFrustumClamp = 1.3f;     // EWA Jacobian: |x/z| <= 1.3 * tan(half fov)
  static constexpr float kMaxAlpha = 0.99f;
  static constexpr float kMinAlpha = 1.0f / 255.0f;
  static constexpr float kMinTransmittance = 1e-4f;
};

struct RenderOptions {
  Eigen::Vector3f background = Eigen::Vector3f::Zero();  // linear RGB added with weight T
  bool want_depth = true;
  bool want_alpha = true;
  // Keep what Engine::RenderBackward needs (per-pixel contributor counts and the frame's splats)
  // until the next Render on this engine. Costs one store per pixel and splat in the blend.
  bool keep_for_backward = false;
  // Asked between stages (and, on the cpu, between batches of tiles) whether the caller has given
  // up (a client's deadline or cancel); when it returns true the render returns CANCELLED without
  // finishing. Called from several threads at once: it must be thread-safe and cheap.
  std::function<bool()> should_stop;
};

// Wall-clock milliseconds per stage of the last render (device time for vulkan when the device
// reports timestamps). upload and readback are not included in the stages.
struct StageTimings {
  double projection_ms = 0;  // projection + SH to RGB (+ visibility compaction)
  double sort_ms = 0;        // depth sort, tile binning, tile sort, tile ranges
  double blend_ms = 0;       // per-tile front-to-back blending
  double total_ms = 0;       // whole frame as seen by the caller, readback included
};

struct RenderStats {
  size_t num_gaussians = 0;
  size_t num_visible = 0;       // passed the near plane / frustum / degeneracy culls
  size_t num_tile_instances = 0;  // (Gaussian, tile) pairs blended
};

struct RenderOutput {
  int width = 0;
  int height = 0;
  std::vector<float> rgb;    // [H*W*3] row-major, linear, background included
  std::vector<float> depth;  // [H*W] sum(z * alpha * T), metres (not normalised by alpha)
  std::vector<float> alpha;  // [H*W] 1 - final transmittance
  StageTimings timings;
  RenderStats stats;
};

// dL/d(outputs) of the last Render, same layouts as RenderOutput. A null pointer means zero.
struct RenderOutputGrads {
  const float* rgb = nullptr;    // [H*W*3]
  const float* depth = nullptr;  // [H*W]
  const float* alpha = nullptr;  // [H*W]
};

struct BackwardOptions {
  // Fixed-order reduction: identical bits run to run and for any thread count (slower).
  bool deterministic = false;
};

// dL/d(raw parameters) in GaussianStore layouts, sized for the scene rendered (sh: K of the
// uploaded scene's degree), plus per-Gaussian screen-space quantities densification needs.
struct GaussianGrads {
  std::vector<float> means;           // [N*3]
  std::vector<float> log_scales;      // [N*3]
  std::vector<float> rotations;       // [N*4]
  std::vector<float> opacity_logits;  // [N]
  std::vector<float> sh;              // [N*K*3]
  std::vector<float> means2d;         // [N*2] dL/d(u, v) of the projected mean, pixels
  std::vector<float> radii;           // [N] 3DGS screen radius ceil(3 sqrt(lambda_max)); 0 = not visible
  double backward_ms = 0;             // wall time of the backward pass
  double blend_backward_ms = 0;       // of which the per-pixel replay (0 where a backend does not say)
};

// Training: Gaussian parameters in the caller's layout (the GaussianStore one, but SH with a stride
// of `sh_stride` coefficients per channel of which the first ShCoeffsForDegree(sh_degree) are
// uploaded), for Engine::UpdateSceneParams. Pointers must stay valid for the call only.
struct GaussianParamsView {
  size_t n = 0;
  int sh_degree = 0;                      // degree to upload
  int sh_stride = 0;                      // coefficients per channel per Gaussian in `sh` (>= K)
  const float* means = nullptr;           // [n*3]
  const float* log_scales = nullptr;      // [n*3]
  const float* rotations = nullptr;       // [n*4] (w, x, y, z)
  const float* opacity_logits = nullptr;  // [n]
  const float* sh = nullptr;              // [n*sh_stride*3]
};

// Which parameters of which Gaussians changed since a scene's last update (serving a dynamic scene:
// the moving Gaussians' positions and colours), for Engine::UpdateSceneRows and the LiDAR
// renderer's UpdateRows. Every other value is the same as in that update.
struct ParamsChange {
  const uint32_t* rows = nullptr;  // distinct rows
  size_t num_rows = 0;
  bool means = false, log_scales = false, rotations = false, opacity = false;
  int sh_coeffs = 0;  // the first sh_coeffs SH coefficients of each channel changed (0: none)
};

// A scene's copy as planes in host memory (Engine::WritablePlanes): plane per parameter, Gaussian i
// at index i. SH plane (k*3 + c) holds coefficient k of channel c: sh[(k*3 + c)*sh_plane + i];
// `sh` is 64-byte aligned and sh_plane a multiple of 16 floats, so a run of 16 Gaussians from a
// multiple of 16 is one cache line of each SH plane.
struct ScenePlanes {
  size_t n = 0;
  int sh_degree = 0;
  float* mean[3] = {};
  float* log_scale[3] = {};
  float* rotation[4] = {};  // w, x, y, z
  float* opacity_logit = nullptr;
  float* sh = nullptr;
  size_t sh_plane = 0;
};

// A scene living in a backend's memory. Opaque; created by Engine::Upload.
class DeviceScene {
 public:
  virtual ~DeviceScene() = default;
  virtual size_t size() const = 0;
  virtual int sh_degree() const = 0;
};

class Engine {
 public:
  virtual ~Engine() = default;
  virtual Backend backend() const = 0;
  // Human-readable device description, e.g. "cpu: 2 threads, avx512" or "vulkan: llvmpipe (...)".
  virtual std::string device_name() const = 0;

  // Validates the store and copies it into backend memory.
  virtual absl::StatusOr<std::unique_ptr<DeviceScene>> Upload(const GaussianStore& store) = 0;

  // Renders one frame. `out` buffers are reused across calls when sizes match.
  virtual absl::Status Render(const DeviceScene& scene, const PinholeCamera& camera,
                              const RenderOptions& options, RenderOutput* out) = 0;

  // Gradients of a scalar loss with respect to every Gaussian parameter of `scene`, given
  // dL/d(outputs) of the last Render on this engine, which must have rendered `scene` with
  // keep_for_backward set (3DGS backward: per-tile back-to-front replay). Backends without a
  // backward pass return Unimplemented.
  virtual absl::Status RenderBackward(const DeviceScene& scene, const RenderOutputGrads& grads,
                                      const BackwardOptions& options, GaussianGrads* out) {
    return absl::UnimplementedError(
        absl::StrCat(device_name(), ": this backend has no backward pass yet"));
  }

  // Replaces the parameters of an uploaded scene (training: once per step) without reallocating
  // when the size is unchanged. The default re-uploads.
  virtual absl::Status UpdateScene(const GaussianStore& store, std::unique_ptr<DeviceScene>* scene) {
    absl::StatusOr<std::unique_ptr<DeviceScene>> s = Upload(store);
    if (!s.ok()) return s.status();
    *scene = std::move(*s);
    return absl::OkStatus();
  }

  // Training: like UpdateScene from a view of the parameters (no GaussianStore copy). Backends may
  // update their copy in place and check only what rendering needs (finite values, non-zero
  // rotations). The default copies into a store and calls UpdateScene.
  virtual absl::Status UpdateSceneParams(const GaussianParamsView& params, std::unique_ptr<DeviceScene>* scene) {
    GaussianStore store;
    store.sh_degree = params.sh_degree;
    const size_t n = params.n;
    const int K = ShCoeffsForDegree(params.sh_degree);
    if (params.sh_stride < K) return absl::InvalidArgumentError("UpdateSceneParams: sh_stride < SH coefficients");
    store.means.assign(params.means, params.means + n * 3);
    store.log_scales.assign(params.log_scales, params.log_scales + n * 3);
    store.rotations.assign(params.rotations, params.rotations + n * 4);
    store.opacity_logits.assign(params.opacity_logits, params.opacity_logits + n);
    store.sh.resize(n * K * 3);
    for (size_t i = 0; i < n; ++i)
      for (int k = 0; k < K * 3; ++k) store.sh[i * K * 3 + k] = params.sh[i * params.sh_stride * 3 + k];
    return UpdateScene(store, scene);
  }

  // Serving: like UpdateSceneParams when only `change` differs from the scene's last update (the
  // same Gaussians otherwise). Backends may copy and check just those values; the default updates
  // everything.
  virtual absl::Status UpdateSceneRows(const GaussianParamsView& params, const ParamsChange& change,
                                       std::unique_ptr<DeviceScene>* scene) {
    return UpdateSceneParams(params, scene);
  }

  // Serving: the engine's own copy of `scene` as planes that a writer overwrites in place between
  // renders (field::HostPlanesWriter writes the serving form's new time there, instead of into a
  // store that UpdateSceneRows then copies), for backends whose copy lives in host memory in that
  // layout (the cpu backend in float precision); Unimplemented elsewhere. Valid until the scene is
  // next uploaded, updated or destroyed. Nothing checks what is written: the writer must write
  // finite values and non-zero rotations.
  virtual absl::StatusOr<ScenePlanes> WritablePlanes(DeviceScene* scene) {
    return absl::UnimplementedError(absl::StrCat(device_name(), ": no writable planes of a scene"));
  }
};

// Creates an engine. kAuto: vulkan when a real (non-CPU) Vulkan GPU is present, else cpu.
absl::StatusOr<std::unique_ptr<Engine>> CreateEngine(Backend backend);

}  // namespace streetsim
