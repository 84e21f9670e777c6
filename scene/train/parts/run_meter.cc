#include "scene/train/parts/run_meter.h"

#include <algorithm>

namespace streetsim::train {

RunMeter::RunMeter(int64_t first, int64_t iterations, int64_t stage_end, Clock::time_point t_start)
    : first_(first), iterations_(iterations), stage_end_(stage_end), t_start_(t_start) {}

double RunMeter::Seconds(Clock::time_point since) const {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

void RunMeter::Observe(int64_t it, double loss, double psnr, size_t gaussians, TrainState* st, TrainResult* result,
                       const std::function<void(const Progress&)>& progress) {
  recent_psnr_.push_back(psnr);
  psnr_window_ += psnr;
  if (recent_psnr_.size() > 50) {
    psnr_window_ -= recent_psnr_.front();
    recent_psnr_.erase(recent_psnr_.begin());
  }
  recent_loss_ = recent_loss_ == 0 ? loss : 0.9 * recent_loss_ + 0.1 * loss;
  const double mean_psnr = psnr_window_ / recent_psnr_.size();
  result->train_psnr_mean50 = mean_psnr;
  if (result->seconds_to_psnr24 < 0 && recent_psnr_.size() >= 50 && mean_psnr >= 24) {
    result->seconds_to_psnr24 = Seconds(t_start_);
  }
  if (it % 10 == 0 || it == iterations_) {
    st->curve.push_back(static_cast<double>(it));
    st->curve.push_back(recent_loss_);
    st->curve.push_back(mean_psnr);
  }
  const bool staged = stage_end_ < iterations_;
  if (staged && it == stage_end_) {  // the next stage's rate is measured from here
    rate_window_.clear();
    rate_window_.emplace_back(it, Seconds(t_loop_));
  }
  if (!progress || !(it % 10 == 0 || it == iterations_ || it == first_)) return;
  Progress p;
  p.iteration = it;
  p.total = iterations_;
  p.loss = loss;
  p.psnr = psnr;
  p.gaussians = gaussians;
  const double now_s = Seconds(t_loop_);
  if (rate_window_.empty() || rate_window_.back().first != it) rate_window_.emplace_back(it, now_s);
  while (rate_window_.size() > 11) rate_window_.pop_front();  // ~100 iterations
  const auto& [it0, t0_s] = rate_window_.front();
  p.it_per_s = it0 < it ? (it - it0) / std::max(now_s - t0_s, 1e-9) : (it - first_ + 1) / std::max(now_s, 1e-9);
  p.eta_static_stage_only = staged && it <= stage_end_;
  p.eta_s = ((p.eta_static_stage_only ? stage_end_ : iterations_) - it) / std::max(p.it_per_s, 1e-9);
  progress(p);
}

}  // namespace streetsim::train
