// The image outputs of `streetsim eval` beside its metrics (docs/training.md "Eval outputs"):
// --decomposition DIR (decomposition.h: full / static / dynamic renders per view, and the
// dynamic-pixel mask) and --video PATH (eval_video.h: rendered | ground truth [| dynamic only]).
// Both hang off the evaluation as its EvalFrameSink (evaluate.h), so the video shows exactly the
// renders that were measured.
#pragma once

#include <memory>
#include <optional>
#include <string>

#include <Eigen/Core>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/field/deformation_field.h"
#include "scene/gaussians/gaussian_store.h"
#include "scene/eval/decomposition.h"
#include "scene/eval/eval_video.h"
#include "scene/eval/evaluate.h"

namespace streetsim::train {

struct EvalOutputOptions {
  std::string decomposition_dir;  // empty: no decomposition images
  std::string video_path;         // empty: no video
  double video_fps = 0;           // <= 0: from the evaluated frames' times
};

// What can fail before the (long) evaluation: creates decomposition_dir (and its parents), checks
// the video's extension and directory. InvalidArgument / NotFound: bad arguments.
absl::Status PrepareEvalOutputs(const EvalOutputOptions& options);

struct EvalOutputSummary {
  // Static / dynamic Gaussians (decomposition.h) summed over the scenes used (a clip set: one per
  // clip); set when the split was computed (--decomposition, or --video of a field scene).
  struct Split {
    int scenes = 0;
    int scenes_with_field = 0;
    size_t static_gaussians = 0, dynamic_gaussians = 0;
  };
  std::optional<Split> split;
  int decomposition_views = 0;  // views whose images were written
  std::optional<VideoSummary> video;
};

class EvalOutputs {
 public:
  // Checks the options (PrepareEvalOutputs); then UseScene before evaluating.
  static absl::StatusOr<std::unique_ptr<EvalOutputs>> Create(Engine& engine, const EvalOutputOptions& options);
  // The scene the next views are rendered from (`canonical` must outlive its use; `field` null for
  // a static scene; `background` its learned one). A clip set calls it once per clip.
  absl::Status UseScene(const GaussianStore& canonical, std::shared_ptr<const field::DeformationField> field,
                        const Eigen::Vector3f& background);
  // For EvaluateViews / EvaluateSceneDir; valid while this object is.
  EvalFrameSink sink();
  // Writes the video (after the evaluation).
  absl::StatusOr<EvalOutputSummary> Finish();

 private:
  EvalOutputs(Engine& engine, EvalOutputOptions options) : engine_(engine), options_(std::move(options)) {}
  absl::Status AddView(const View& view, const std::vector<float>& rgb);

  Engine& engine_;
  EvalOutputOptions options_;
  std::unique_ptr<Decomposer> decomposer_;
  std::unique_ptr<EvalVideo> video_;
  EvalOutputSummary summary_;
};

}  // namespace streetsim::train
