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

// Every seam of `set` (a clip set in `set_dir`, trained from `log`), rendered at
// `resolution_scale` (the scenes' training scale). Each clip scene is loaded as `streetsim eval`
// loads it (scene.ply, field.bin if any, its learned sky). Errors: a clip directory or scene
// that cannot be read, a log with fewer frames than the set's.
absl::StatusOr<std::vector<ClipSeam>> MeasureClipSeams(Engine& engine, const std::string& set_dir, const ClipSet& set,
                                                       const DriveLog& log, double resolution_scale);

}  // namespace streetsim::train
