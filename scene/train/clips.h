// Clip sets (S3Gaussian spec 1.2 and 8; docs/training.md "Clips"): a log longer than a clip is
// trained as consecutive clips of N frames, each a scene directory of its own (DIR/clip_KKK/),
// listed in DIR/clips.json. This module plans the clips, reads and writes the manifest, picks the
// clip for a time and merges per-clip metrics; the training itself is clip_training.h.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "scene/train/dataset.h"
#include "scene/eval/lidar_eval.h"
#include "scene/train/trainer.h"

namespace streetsim::train {

inline constexpr char kClipManifestName[] = "clips.json";
// Shorter clips are refused: with the default hold-out (every 4th frame) a clip of 4 frames is the
// shortest that always keeps a held-out frame, and a field fitted to fewer frames has no motion
// to learn.
inline constexpr int kMinClipFrames = 4;

// Frames [first_frame, end_frame) of the log.
struct ClipRange {
  int first_frame = 0;
  int end_frame = 0;
  int size() const { return end_frame - first_frame; }
  bool operator==(const ClipRange& o) const { return first_frame == o.first_frame && end_frame == o.end_frame; }
};

// Clip k = frames [k N, (k + 1) N); the remainder r = num_frames mod N is a clip of its own when
// r >= ceil(N / 2), else it joins the last full clip (so every clip has N / 2 .. 1.5 N frames, and
// a log of at most 1.5 N frames is one clip). clip_frames = 0: one clip over the whole log.
// Errors: clip_frames < 0, 0 < clip_frames < kMinClipFrames, num_frames < 1.
absl::StatusOr<std::vector<ClipRange>> PlanClips(int num_frames, int clip_frames);

// The frames a clip trains on: its own frames and `overlap_frames` of each neighbour's (clamped to
// the log), so that at a switch between two clips both have been fitted to the frames around it
// (docs/training.md "Clips", overlap).
ClipRange TrainedFrames(const ClipRange& frames, int overlap_frames, int num_frames);
// `streetsim train`'s --clip-overlap when none is given: a tenth of a clip on each side (50 -> 5;
// measured in docs/training.md "Clips").
inline int DefaultClipOverlap(int clip_frames) { return clip_frames / 10; }
// --clip-overlap: 0 .. clip_frames / 2 (a larger overlap would train a clip on more of its
// neighbours' frames than of its own). Errors name the flag.
absl::Status CheckClipOverlap(int clip_frames, int overlap_frames);

struct ClipEntry {
  ClipRange frames;                  // the frames it serves and is evaluated on
  int64_t start_us = 0, end_us = 0;  // times of its first and last frame (`frames`)
  std::string dir;                   // relative to the clip set: ClipDirName(index)
  bool done = false;                 // trained to the end, outputs written
};

// DIR/clips.json.
struct ClipSet {
  int clip_frames = 0;     // --clip-frames
  int overlap_frames = 0;  // --clip-overlap
  int num_frames = 0;      // frames of the log
  std::vector<ClipEntry> clips;
  // The frames clip k is trained on (its own and the overlap).
  ClipRange trained(size_t k) const { return TrainedFrames(clips[k].frames, overlap_frames, num_frames); }
};

std::string ClipDirName(int index);  // "clip_000"
// The plan of a log as a manifest (done = false everywhere).
ClipSet MakeClipSet(const DriveLog& log, int clip_frames, const std::vector<ClipRange>& plan, int overlap_frames = 0);
// The log restricted to frames [first, end) (a clip's own log: its scene.json, its views).
DriveLog ClipLog(const DriveLog& log, const ClipRange& frames);
// Written to a temporary file and renamed into place.
absl::Status WriteClipSet(const ClipSet& set, const std::string& dir);
// nullopt when DIR has no clips.json. Anything malformed is a DataLoss error naming the file:
// bad JSON, missing or mistyped keys, clips that are not consecutive frame ranges in time order,
// trained frames other than TrainedFrames of the clip's, a directory other than clip_KKK of its
// index (nothing that could leave DIR). A manifest without "overlap_frames" (written before
// overlaps existed) has none.
absl::StatusOr<std::optional<ClipSet>> ReadClipSet(const std::string& dir);

// The clip for a time: the one whose [start_us, end_us] holds it; between two clips the nearer
// (a tie goes to the earlier); before the first / after the last clip, the first / last.
int PickClip(const ClipSet& set, int64_t time_us);
// DIR/<clip's dir>, after checking that the directory exists and resolves inside DIR (a clip
// directory that is a link out of DIR is refused).
absl::StatusOr<std::string> ClipPath(const std::string& dir, const ClipEntry& clip);

// What `streetsim render --scene DIR` renders: DIR itself, or for a clip set the clip of
// `time_us` (without a time: the first clip, i.e. the log's first time).
absl::StatusOr<std::string> SceneDirForTime(const std::string& dir, std::optional<int64_t> time_us);

// Views grouped by the clip of their time: result[k] = indices into `views` of clip k, in order.
std::vector<std::vector<size_t>> GroupViewsByClip(const ClipSet& set, const std::vector<View>& views);

// Per-clip metrics as one result: frames concatenated in the given order, means recomputed with
// the rules of EvaluateViews / EvaluateLidar (over the frames where each metric is defined).
EvalResult MergeEvalResults(const std::vector<EvalResult>& parts);
LidarEvalResult MergeLidarEvalResults(const std::vector<LidarEvalResult>& parts);

}  // namespace streetsim::train
