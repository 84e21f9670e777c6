#include "scene/train/divergence_guard.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace streetsim::train {

void DivergenceGuard::Restore(const DivergenceGuardState& s) {
  started_ = s.started;
  baseline_ = s.baseline;
  mean_ = s.mean;
  best_ = s.best;
  psnr_mean_ = s.psnr_mean;
  psnr_best_ = s.psnr_best;
}

void DivergenceGuard::Rebaseline(int64_t iteration) {
  baseline_ = iteration;
  best_ = 0;
  psnr_best_ = 0;
}

DivergenceGuard::Verdict DivergenceGuard::Observe(int64_t iteration, double loss, double psnr_db) {
  why_.clear();
  if (!std::isfinite(loss)) {
    why_ = "the training loss is not finite";
    return Verdict::kDiverged;
  }
  if (!std::isfinite(psnr_db)) psnr_db = psnr_mean_;  // a perfect view: no evidence either way
  if (!started_) {
    started_ = true;
    baseline_ = iteration;
    mean_ = loss;
    psnr_mean_ = psnr_db;
  }
  mean_ += options_.mean_weight * (loss - mean_);
  psnr_mean_ += options_.mean_weight * (psnr_db - psnr_mean_);
  if (iteration - baseline_ < options_.grace_iterations) return Verdict::kFine;
  if (best_ <= 0 || mean_ < best_) best_ = mean_;
  if (psnr_best_ <= 0 || psnr_mean_ > psnr_best_) psnr_best_ = psnr_mean_;
  const double drop_db = psnr_best_ - psnr_mean_;
  auto say = [&](const char* level) {
    why_ = absl::StrCat("the training loss's running mean is ", mean_, " (", mean_ / best_, "x its best, ", best_,
                        ") and the training views' PSNR ", psnr_mean_, " dB (", drop_db, " dB below its best): ", level);
  };
  if (mean_ > options_.diverged_ratio * best_ || drop_db > options_.diverged_drop_db) {
    say("diverged");
    return Verdict::kDiverged;
  }
  if (mean_ > options_.suspicious_ratio * best_ || drop_db > options_.suspicious_drop_db) {
    say("suspicious");
    return Verdict::kSuspicious;
  }
  return Verdict::kFine;
}

}  // namespace streetsim::train
