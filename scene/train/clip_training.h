// Training a log clip by clip (S3Gaussian spec 8; docs/training.md "Clips"): clip k of the plan
// (clips.h PlanClips) trains frames [first, end) into DIR/clip_KKK/, a normal scene directory,
// from new Gaussians of its own training frames' LiDAR; with --field s3gaussian its fine stage
// starts from clip k-1's field.bin (FieldOptions::prior). DIR/clips.json records the plan and which
// clips are done, so that --resume continues in the clip a run was killed in.
#pragma once

#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/log/drive_log.h"
#include "scene/train/clips.h"
#include "scene/train/trainer.h"

namespace streetsim::train {

struct ClipTrainOptions {
  int clip_frames = 0;  // 0: one clip (a plain scene directory, exactly Train's)
  // Each clip also trains on this many frames of each neighbour (clips.h TrainedFrames); 0 ..
  // clip_frames / 2 (0: S3Gaussian's plan); without effect on a one-clip plan. Unset: on resume
  // the set's own, else DefaultClipOverlap(clip_frames).
  std::optional<int> overlap_frames;
  // Testing: the clip whose run TrainOptions::stop_after stops (as if killed); -1: any clip's.
  int stop_in_clip = -1;
};

struct ClipRun {
  int clip = 0;
  ClipRange frames;   // the frames it serves (ClipEntry::frames)
  ClipRange trained;  // the frames it trained on (ClipEntry::trained)
  std::string dir;
  TrainResult result;
};

struct ClipTrainResult {
  std::optional<ClipSet> set;  // nullopt: one clip, trained into DIR itself
  std::vector<ClipRun> runs;   // the clips this call trained or continued (done ones are skipped)
  bool stopped = false;        // a run stopped at TrainOptions::stop_after
};

// Plans the clips of `log` and trains every clip that is not done. One clip: Train(log, out_dir)
// (a stale DIR/clips.json is removed; --resume of a clip set without --clip-frames is refused).
// Clip k trains with seed options.seed + k on its trained frames (its own and the overlap), its
// field's time axis over their times.
absl::StatusOr<ClipTrainResult> TrainClips(const DriveLog& log, const std::string& out_dir,
                                           const TrainOptions& options, const ClipTrainOptions& clip_options,
                                           const std::function<void(const Progress&)>& progress = nullptr);

// One clip: the views of frames [first, end) split by the log-wide hold-out rule (View::frame is
// the log's frame index), the initial scene from its training frames, then TrainOnViews.
absl::StatusOr<TrainResult> TrainClip(const DriveLog& log, const ClipRange& frames, const std::string& dir,
                                      const TrainOptions& options,
                                      const std::function<void(const Progress&)>& progress = nullptr);

}  // namespace streetsim::train
