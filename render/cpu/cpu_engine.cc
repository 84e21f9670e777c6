#include "render/cpu/cpu_engine.h"

#include <chrono>
#include <thread>

#include "absl/strings/str_cat.h"
#include "render/common/thread_pool.h"
#include "render/cpu/binning.h"
#include "render/cpu/blend.h"
#include "render/cpu/blend_backward.h"
#include "render/cpu/project_bwd.h"
#include "render/cpu/project.h"

namespace streetsim {
namespace {

using Clock = std::chrono::steady_clock;
double MsSince(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

bool Stopped(const RenderOptions& options) { return options.should_stop && options.should_stop(); }
absl::Status StoppedError() { return absl::CancelledError("render stopped by its caller"); }

// The cpu backend's "device memory": a host copy of the scene, so the caller may free or change
// its own store after Upload. The vectorised path keeps it as one array per parameter
// (SceneSoa); the scalar reference paths keep the store layout they index directly.
class CpuScene final : public DeviceScene {
 public:
  CpuScene(const GaussianStore& store, bool soa) : sh_degree_(store.sh_degree), size_(store.size()) {
    if (soa) {
      soa_ = cpu::SceneSoa::FromStore(store);
    } else {
      store_ = store;
    }
  }
  size_t size() const override { return size_; }
  int sh_degree() const override { return sh_degree_; }
  const GaussianStore& store() const { return store_; }
  const cpu::SceneSoa& soa() const { return soa_; }
  cpu::SceneSoa& mutable_soa() { return soa_; }
  void SetShape(size_t size, int sh_degree) { size_ = size, sh_degree_ = sh_degree; }
  // Training: new parameters, same layout choice; vectors keep their capacity.
  void Replace(const GaussianStore& store, bool soa) {
    sh_degree_ = store.sh_degree;
    size_ = store.size();
    if (soa) {
      soa_ = cpu::SceneSoa::FromStore(store);
    } else {
      store_ = store;
    }
  }

 private:
  int sh_degree_;
  size_t size_;
  GaussianStore store_;
  cpu::SceneSoa soa_;
};

class CpuEngine final : public Engine {
 public:
  explicit CpuEngine(const CpuEngineOptions& options)
      : options_(options), pool_(options.num_threads) {}

  Backend backend() const override { return Backend::kCpu; }
  std::string device_name() const override {
    const char* mode = options_.precision == CpuPrecision::kFloatSimd     ? cpu::BlendSimdIsa()
                       : options_.precision == CpuPrecision::kFloatScalar ? "scalar float"
                                                                          : "scalar double";
    return absl::StrCat("cpu: ", pool_.num_threads(), " threads, ", mode);
  }

  absl::StatusOr<std::unique_ptr<DeviceScene>> Upload(const GaussianStore& store) override {
    if (absl::Status s = store.Validate(); !s.ok()) return s;
    if (store.size() > (1u << 30)) {
      return absl::InvalidArgumentError(absl::StrCat("scene has ", store.size(),
                                                     " Gaussians; the cpu backend takes <= 2^30"));
    }
    return std::make_unique<CpuScene>(store, options_.precision == CpuPrecision::kFloatSimd);
  }

  absl::Status Render(const DeviceScene& scene, const PinholeCamera& camera,
                      const RenderOptions& options, RenderOutput* out) override {
    const auto* cpu_scene = dynamic_cast<const CpuScene*>(&scene);
    if (cpu_scene == nullptr) {
      return absl::InvalidArgumentError("scene was not uploaded by the cpu backend");
    }
    if (absl::Status s = camera.Validate(); !s.ok()) return s;
    if (!options.background.allFinite()) {
      return absl::InvalidArgumentError("background colour is not finite");
    }
    kept_scene_ = nullptr;
    if (options_.precision == CpuPrecision::kDouble) {
      return RenderImpl<double>(*cpu_scene, camera, options, &frame_d_, out);
    }
    return RenderImpl<float>(*cpu_scene, camera, options, &frame_f_, out);
  }

  absl::Status UpdateScene(const GaussianStore& store, std::unique_ptr<DeviceScene>* scene) override {
    auto* cpu_scene = scene->get() ? dynamic_cast<CpuScene*>(scene->get()) : nullptr;
    if (cpu_scene == nullptr) return Engine::UpdateScene(store, scene);
    if (absl::Status s = store.Validate(); !s.ok()) return s;
    if (store.size() > (1u << 30)) return absl::InvalidArgumentError("scene too large for the cpu backend");
    cpu_scene->Replace(store, options_.precision == CpuPrecision::kFloatSimd);
    if (kept_scene_ == cpu_scene) kept_scene_ = nullptr;
    return absl::OkStatus();
  }

  // Training: the SoA copy is overwritten in place (no store, no allocation when the size is
  // unchanged, no full validation: finiteness and zero rotations are checked while copying).
  absl::Status UpdateSceneParams(const GaussianParamsView& params, std::unique_ptr<DeviceScene>* scene) override {
    auto* cpu_scene = scene->get() ? dynamic_cast<CpuScene*>(scene->get()) : nullptr;
    if (cpu_scene == nullptr || options_.precision != CpuPrecision::kFloatSimd) {
      return Engine::UpdateSceneParams(params, scene);
    }
    if (params.n > (1u << 30)) return absl::InvalidArgumentError("scene too large for the cpu backend");
    if (kept_scene_ == cpu_scene) kept_scene_ = nullptr;
    absl::Status s = cpu_scene->mutable_soa().Assign(pool_, params);
    cpu_scene->SetShape(params.n, params.sh_degree);
    if (!s.ok()) {
      cpu_scene->mutable_soa() = cpu::SceneSoa();  // do not leave a half-written scene renderable
      cpu_scene->SetShape(0, params.sh_degree);
    }
    return s;
  }

  absl::Status UpdateSceneRows(const GaussianParamsView& params, const ParamsChange& change,
                               std::unique_ptr<DeviceScene>* scene) override {
    auto* cpu_scene = scene->get() ? dynamic_cast<CpuScene*>(scene->get()) : nullptr;
    if (cpu_scene == nullptr || options_.precision != CpuPrecision::kFloatSimd || cpu_scene->soa().n != params.n ||
        cpu_scene->soa().sh_degree != params.sh_degree) {
      return UpdateSceneParams(params, scene);
    }
    if (kept_scene_ == cpu_scene) kept_scene_ = nullptr;
    absl::Status s = cpu_scene->mutable_soa().AssignRows(pool_, params, change);
    if (!s.ok()) {
      cpu_scene->mutable_soa() = cpu::SceneSoa();  // do not leave a half-written scene renderable
      cpu_scene->SetShape(0, params.sh_degree);
    }
    return s;
  }

  absl::StatusOr<ScenePlanes> WritablePlanes(DeviceScene* scene) override {
    auto* cpu_scene = dynamic_cast<CpuScene*>(scene);
    if (cpu_scene == nullptr || options_.precision != CpuPrecision::kFloatSimd) {
      return Engine::WritablePlanes(scene);
    }
    if (kept_scene_ == cpu_scene) kept_scene_ = nullptr;  // the kept forward no longer matches
    cpu::SceneSoa& s = cpu_scene->mutable_soa();
    ScenePlanes p;
    p.n = s.n;
    p.sh_degree = s.sh_degree;
    p.mean[0] = s.mx.data(), p.mean[1] = s.my.data(), p.mean[2] = s.mz.data();
    p.log_scale[0] = s.ls0.data(), p.log_scale[1] = s.ls1.data(), p.log_scale[2] = s.ls2.data();
    p.rotation[0] = s.qw.data(), p.rotation[1] = s.qx.data(), p.rotation[2] = s.qy.data(), p.rotation[3] = s.qz.data();
    p.opacity_logit = s.opacity_logit.data();
    p.sh = s.sh.data();
    p.sh_plane = s.sh_plane;
    return p;
  }

  absl::Status RenderBackward(const DeviceScene& scene, const RenderOutputGrads& grads,
                              const BackwardOptions& options, GaussianGrads* out) override {
    const auto t0 = Clock::now();
    const auto* cpu_scene = dynamic_cast<const CpuScene*>(&scene);
    if (cpu_scene == nullptr || cpu_scene != kept_scene_) {
      return absl::FailedPreconditionError(
          "RenderBackward needs the last Render of this scene on this engine with keep_for_backward");
    }
    if (grads.rgb == nullptr) return absl::InvalidArgumentError("RenderBackward: dL/drgb is required");
    if (options_.precision == CpuPrecision::kDouble) {
      const cpu::Frame<double>& f = frame_d_;
      const size_t pixels = static_cast<size_t>(f.width) * f.height;
      std::vector<double> g_rgb(grads.rgb, grads.rgb + pixels * 3), g_d, g_a;
      if (grads.depth) g_d.assign(grads.depth, grads.depth + pixels);
      if (grads.alpha) g_a.assign(grads.alpha, grads.alpha + pixels);
      cpu::BlendBackwardArgs<double> args;
      args.frame = &f;
      for (int c = 0; c < 3; ++c) args.background[c] = kept_background_[c];
      args.d_rgb = g_rgb.data();
      args.d_depth = grads.depth ? g_d.data() : nullptr;
      args.d_alpha = grads.alpha ? g_a.data() : nullptr;
      cpu::BlendBackwardScalar<double>(pool_, args, &bwd_scratch_d_, &splat_grads_d_);
      cpu::ProjectBackwardStore<double>(pool_, cpu_scene->store(), kept_cam_d_, f, splat_grads_d_, out);
    } else {
      cpu::BlendBackwardArgs<float> args;
      args.frame = &frame_f_;
      for (int c = 0; c < 3; ++c) args.background[c] = kept_background_[c];
      args.d_rgb = grads.rgb;
      args.d_depth = grads.depth;
      args.d_alpha = grads.alpha;
      if (options_.precision == CpuPrecision::kFloatSimd) {
        cpu::BlendBackwardSimd(pool_, args, options.deterministic, &bwd_scratch_f_, &splat_grads_f_);
        out->blend_backward_ms = MsSince(t0);
        cpu::ProjectBackwardSoa(pool_, cpu_scene->soa(), kept_cam_f_, frame_f_, splat_grads_f_, out);
      } else {
        cpu::BlendBackwardScalar<float>(pool_, args, &bwd_scratch_f_, &splat_grads_f_);
        cpu::ProjectBackwardStore<float>(pool_, cpu_scene->store(), kept_cam_f_, frame_f_, splat_grads_f_, out);
      }
    }
    out->backward_ms = MsSince(t0);
    return absl::OkStatus();
  }

 private:
  template <typename Real>
  absl::Status RenderImpl(const CpuScene& scene, const PinholeCamera& camera,
                          const RenderOptions& options, cpu::Frame<Real>* frame,
                          RenderOutput* out) {
    const auto t_start = Clock::now();
    const auto cam = cpu::MakeCameraParams<Real>(camera);
    frame->width = camera.width;
    frame->height = camera.height;
    frame->tiles_x = cam.tiles_x;
    frame->tiles_y = cam.tiles_y;

    auto t0 = Clock::now();
    if constexpr (std::is_same_v<Real, float>) {
      if (options_.precision == CpuPrecision::kFloatSimd) {
        cpu::ProjectGaussiansSimd(pool_, scene.soa(), cam, frame);
      } else {
        cpu::ProjectGaussians<Real>(pool_, scene.store(), cam, frame);
      }
    } else {
      cpu::ProjectGaussians<Real>(pool_, scene.store(), cam, frame);
    }
    out->timings.projection_ms = MsSince(t0);
    if (Stopped(options)) return StoppedError();

    t0 = Clock::now();
    cpu::SortByDepth(frame);
    cpu::BinTiles(pool_, frame);
    out->timings.sort_ms = MsSince(t0);
    if (Stopped(options)) return StoppedError();

    const size_t pixels = static_cast<size_t>(camera.width) * camera.height;
    out->width = camera.width;
    out->height = camera.height;
    frame->final_T.resize(pixels);
    frame->n_contrib.resize(pixels);

    t0 = Clock::now();
    if constexpr (std::is_same_v<Real, float>) {
      out->rgb.resize(pixels * 3);
      out->depth.resize(options.want_depth ? pixels : 0);
      out->alpha.resize(options.want_alpha ? pixels : 0);
      cpu::BlendArgs<float> args;
      args.frame = frame;
      for (int c = 0; c < 3; ++c) args.background[c] = options.background[c];
      args.rgb = out->rgb.data();
      args.depth = options.want_depth ? out->depth.data() : nullptr;
      args.alpha = options.want_alpha ? out->alpha.data() : nullptr;
      args.final_T = frame->final_T.data();
      // The backward pass (training) needs the per-pixel contributor counts; plain rendering
      // skips them (one store less per pixel and splat in the blend).
      args.n_contrib = options.keep_for_backward ? frame->n_contrib.data() : nullptr;
      args.should_stop = options.should_stop ? &options.should_stop : nullptr;
      if (options_.precision == CpuPrecision::kFloatSimd) {
        cpu::BlendSimd(pool_, args);
      } else {
        cpu::BlendScalar<float>(pool_, args);
      }
    } else {
      std::vector<double> rgb(pixels * 3), depth(pixels), alpha(pixels);
      cpu::BlendArgs<double> args;
      args.frame = frame;
      for (int c = 0; c < 3; ++c) args.background[c] = options.background[c];
      args.rgb = rgb.data();
      args.depth = depth.data();
      args.alpha = alpha.data();
      args.final_T = frame->final_T.data();
      args.n_contrib = frame->n_contrib.data();
      args.should_stop = options.should_stop ? &options.should_stop : nullptr;
      cpu::BlendScalar<double>(pool_, args);
      out->rgb.assign(rgb.begin(), rgb.end());
      if (options.want_depth) out->depth.assign(depth.begin(), depth.end()); else out->depth.clear();
      if (options.want_alpha) out->alpha.assign(alpha.begin(), alpha.end()); else out->alpha.clear();
    }
    out->timings.blend_ms = MsSince(t0);
    if (Stopped(options)) return StoppedError();  // batches were skipped: the image is incomplete

    if (options.keep_for_backward) {
      kept_scene_ = &scene;
      kept_background_ = options.background;
      if constexpr (std::is_same_v<Real, float>) {
        kept_cam_f_ = cam;
      } else {
        kept_cam_d_ = cam;
      }
    }
    out->stats.num_gaussians = scene.size();
    out->stats.num_visible = frame->visible_ids.size();
    out->stats.num_tile_instances = frame->tile_ids.size();
    out->timings.total_ms = MsSince(t_start);
    // The per-pixel and per-tile scratch is kept for the next frame of the same size (training,
    // a closed loop), but not after an outsized one: a served 4096x4096 frame would otherwise hold
    // ~130 MB of it for the life of the process.
    if (!options.keep_for_backward && pixels > kKeepScratchPixels) {
      std::vector<Real>().swap(frame->final_T);
      std::vector<uint32_t>().swap(frame->n_contrib);
      std::vector<uint32_t>().swap(frame->tile_ids);
      std::vector<uint32_t>().swap(frame->tile_offsets);
    }
    return absl::OkStatus();
  }

  // Above this a frame's scratch is released after it (a 1920x1080 frame is 2.1 M pixels).
  static constexpr size_t kKeepScratchPixels = size_t{4} << 20;

  CpuEngineOptions options_;
  ThreadPool pool_;
  cpu::Frame<float> frame_f_;
  cpu::Frame<double> frame_d_;
  // What the backward pass needs from the last Render with keep_for_backward.
  const CpuScene* kept_scene_ = nullptr;
  Eigen::Vector3f kept_background_ = Eigen::Vector3f::Zero();
  projection::CameraParams<float> kept_cam_f_{};
  projection::CameraParams<double> kept_cam_d_{};
  cpu::BlendBackwardScratch<float> bwd_scratch_f_;
  cpu::BlendBackwardScratch<double> bwd_scratch_d_;
  std::vector<float> splat_grads_f_;
  std::vector<double> splat_grads_d_;
};

}  // namespace

std::unique_ptr<Engine> CreateCpuEngine(const CpuEngineOptions& options) {
  return std::make_unique<CpuEngine>(options);
}

}  // namespace streetsim
