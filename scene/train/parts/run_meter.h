// What a run reports of itself while it trains: the training-view PSNR over the last 50
// iterations (TrainResult), the loss / PSNR curve kept in the checkpoint (every 10 iterations),
// and the progress line's rate and time estimate (over the last ~100 iterations of the current
// stage: a fine stage runs at a fraction of the static stage's rate).
#pragma once

#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <utility>
#include <vector>

#include "scene/train/train_state.h"
#include "scene/train/trainer.h"

namespace streetsim::train {

class RunMeter {
 public:
  using Clock = std::chrono::steady_clock;
  // `first`: the run's first iteration (a resume's is past 1); `stage_end`: the first stage's last
  // iteration (== `iterations` for a single-stage run); `t_start`: when the run began (the
  // result's seconds_to_psnr24 counts from there, the rate from the meter's construction).
  RunMeter(int64_t first, int64_t iterations, int64_t stage_end, Clock::time_point t_start);

  // After iteration `it` with its loss and training-view PSNR: the running means, the curve in
  // `st`, the result's PSNR fields, and a progress report every 10 iterations.
  void Observe(int64_t it, double loss, double psnr, size_t gaussians, TrainState* st, TrainResult* result,
               const std::function<void(const Progress&)>& progress);

 private:
  double Seconds(Clock::time_point since) const;

  int64_t first_, iterations_, stage_end_;
  Clock::time_point t_start_, t_loop_ = Clock::now();
  std::vector<double> recent_psnr_;
  double psnr_window_ = 0, recent_loss_ = 0;
  std::deque<std::pair<int64_t, double>> rate_window_;  // (iteration, seconds) at progress reports
};

}  // namespace streetsim::train
