// Static / dynamic decomposition of a trained scene (`streetsim eval --decomposition DIR`,
// docs/training.md "Eval outputs"): which Gaussians move is decided by the serving analysis
// (scene/field/static_skip.h AnalyseStatic with the server's StaticSkipOptions: the Δx box over
// the log's time range below 1 cm and ΔSH below 0.01), so the split shown is the split served.
// Per view three renders of the scene deformed at the view's time: every Gaussian, the static
// ones only (on the learned background: the world without its movers) and the dynamic ones only
// (on black, so that only the movers show; their alpha is kept). A scene without a field is all
// static: its dynamic render is black and its static render is the full one, bit for bit.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "render/common/thread_pool.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/field/static_skip.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/train/dataset.h"

namespace streetsim::train {

struct StaticDynamicSplit {
  bool has_field = false;
  std::vector<uint32_t> static_rows;   // ascending
  std::vector<uint32_t> dynamic_rows;  // ascending; with static_rows every row exactly once
};

// `field` null: every Gaussian is static (no analysis runs).
absl::StatusOr<StaticDynamicSplit> SplitStaticDynamic(const field::DeformationField* field,
                                                      const GaussianStore& canonical, ThreadPool& pool,
                                                      const field::StaticSkipOptions& options = {});

// The Gaussians `rows` of `g`, in that order (normals kept when present).
GaussianStore SelectRows(const GaussianStore& g, const std::vector<uint32_t>& rows);

struct DecompositionRenders {
  int width = 0, height = 0;
  std::vector<float> full;           // [H*W*3] linear RGB on the background, unclamped
  std::vector<float> static_only;    // [H*W*3] on the background
  std::vector<float> dynamic_only;   // [H*W*3] on black
  std::vector<float> dynamic_alpha;  // [H*W]
};

class Decomposer {
 public:
  // `canonical` must outlive the Decomposer; `field` may be null (a static scene).
  static absl::StatusOr<std::unique_ptr<Decomposer>> Create(Engine& engine, const GaussianStore& canonical,
                                                            std::shared_ptr<const field::DeformationField> field,
                                                            const Eigen::Vector3f& background);
  // The three renders of `camera` at `time_us` (the field's time, clamped to its range).
  absl::StatusOr<DecompositionRenders> Render(const PinholeCamera& camera, int64_t time_us);
  const StaticDynamicSplit& split() const { return split_; }

 private:
  Decomposer(Engine& engine, const GaussianStore& canonical, std::shared_ptr<const field::DeformationField> field,
             const Eigen::Vector3f& background);
  absl::Status UploadAt(int64_t time_us);

  Engine& engine_;
  const GaussianStore& canonical_;
  std::shared_ptr<const field::DeformationField> field_;
  Eigen::Vector3f background_;
  StaticDynamicSplit split_;
  ThreadPool pool_{0};
  std::unique_ptr<DeviceScene> full_, static_, dynamic_;
  bool uploaded_ = false;
  int64_t uploaded_time_us_ = 0;
};

// Linear RGB [H*W*3] -> CV_8UC3 in R G B order (clamped to [0,1] x 255, rounded, as renders are saved).
cv::Mat RgbToMat8(const std::vector<float>& rgb, int width, int height);

// The ground truth (View::rgb8) with its dynamic pixels (dynamic_pixels.h) blended half-way to
// red; empty when the view has no mask.
cv::Mat DynamicMaskOverlay(const View& view);

// File stem of a view's decomposition images: its name with '/' and other non-name characters
// replaced by '_' and the extension dropped ("image_02/0000000011.png" -> "image_02_0000000011").
std::string DecompositionStem(const View& view);

// Writes DIR/<stem>_full.png, _static.png, _dynamic.png and, when the view has a dynamic-pixel
// mask, _mask.png (each written to a temporary file and renamed into place).
absl::Status WriteDecompositionPngs(const std::string& dir, const View& view, const DecompositionRenders& renders);

// An 8-bit RGB (R G B order) image to PNG / JPEG by extension, atomically.
absl::Status WriteRgbMatAtomic(const std::string& path, const cv::Mat& rgb8);

}  // namespace streetsim::train
