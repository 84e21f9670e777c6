// Seams of a clip set (docs/training.md "Clips"): where a consumer crosses from clip k to clip
// k + 1 (clips.h PickClip), the image jumps from one reconstruction to another. This measures the
// jump on the frames either side of each switch: both clips render the same views, and the
// renders are compared with each other and with the camera images.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "render/engine.h"
#include "scene/log/drive_log.h"
#include "scene/train/clips.h"
#include "scene/train/dataset.h"
#include "scene/train/dynamic_stage.h"

namespace streetsim::train {

struct ClipSeam {
  int clip = 0;                 // the seam between clip `clip` and clip `clip + 1`
  int64_t switch_time_us = 0;   // the first time PickClip gives clip + 1 (microsecond grid)
  std::vector<int> frames;      // clip's last frame and clip + 1's first (log indices)
  size_t views = 0;             // every camera of those frames
  double psnr_between_db = 0;   // mean over the views: clip's render against clip + 1's
  double psnr_before_db = 0;    // mean PSNR of clip's renders against the images
  double psnr_after_db = 0;     // the same for clip + 1's renders
};

// Measures the seams from clip scenes that the caller has loaded anyway (streetsim eval's loop
// over the clips), so that no clip is read twice. Clips come in order, each once; clip k's renders
// of the seam after it wait for clip k + 1.
class ClipSeamMeter {
 public:
  // The seam views of `set` (trained from `log`) at `resolution_scale` (the scenes' training
  // scale). Errors: a log with fewer frames than the set's, a seam without camera views.
  static absl::StatusOr<ClipSeamMeter> Create(const ClipSet& set, const DriveLog& log, double resolution_scale);

  // Clip `clip`'s scene as evaluation renders it, with its learned sky. FailedPrecondition when
  // clips come out of order.
  absl::Status AddClip(Engine& engine, int clip, const SceneForView& scene, const Eigen::Vector3f& background);

  // Every seam; FailedPrecondition until every clip was added.
  absl::StatusOr<std::vector<ClipSeam>> Finish();

 private:
  int num_clips_ = 0, next_clip_ = 0;
  std::vector<ClipSeam> seams_;
  std::vector<std::vector<View>> views_;                     // per seam
  std::vector<std::vector<std::vector<float>>> earlier_;     // per seam: the earlier clip's renders
};

// Every seam of `set` (a clip set in `set_dir`, trained from `log`), rendered at
// `resolution_scale` (the scenes' training scale). Each clip scene is loaded as `streetsim eval`
// loads it (scene.ply, field.bin if any, its learned sky). Errors: a clip directory or scene
// that cannot be read, a log with fewer frames than the set's.
absl::StatusOr<std::vector<ClipSeam>> MeasureClipSeams(Engine& engine, const std::string& set_dir, const ClipSet& set,
                                                       const DriveLog& log, double resolution_scale);

}  // namespace streetsim::train
