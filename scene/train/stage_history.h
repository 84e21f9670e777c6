// The held-out figures at each stage end of a run, against its training time:
// DIR/heldout_history.json and its plot DIR/heldout_curve.png (docs/training.md "Schedules"). A
// preset with a schedule writes its outputs at every stage end, so its history is the
// PSNR-versus-wall-time curve of the run.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace streetsim::train {

inline constexpr char kStageHistoryFile[] = "heldout_history.json";

struct StagePoint {
  int64_t iteration = 0;
  // Training time to this stage end, summed over the runs that finished each stage (a run killed
  // mid-stage loses the time it had spent in it).
  double seconds = 0;
  double psnr = 0, ssim = 0;
};

// NotFound without the file; DataLoss naming it when damaged.
absl::StatusOr<std::vector<StagePoint>> ReadStageHistory(const std::string& dir);
// Adds a stage end that took `seconds`: after the points before `iteration` (a point at it or
// later, from a run rolled back or restarted, is replaced), its time on top of theirs. Writes the
// file and the plot atomically.
absl::Status AppendStagePoint(const std::string& dir, int64_t iteration, double seconds, double psnr, double ssim);
// Held-out PSNR against hours of training; an RGB image. Fewer than two points: an empty plot.
cv::Mat PlotStageHistory(const std::vector<StagePoint>& points);

}  // namespace streetsim::train
