// Watches a run's training loss and says when it diverges (docs/training.md "Divergence guard").
// A field whose rates are too high for a log (a moving ego, other streets) can blow the loss up
// within a few hundred iterations and densification then inflates the ruined scene; the guard lets
// the trainer keep its last good checkpoint and stop, so that the run goes on from there with
// lower rates instead of ending worse than its static model.
//
// Judged on running means of the loss and of the training views' PSNR against their best since
// the baseline: "suspicious" when the loss is above suspicious_ratio x its best or the PSNR
// suspicious_drop_db below its best (the trainer writes no periodic checkpoint then, so the one on
// disk is from before), "diverged" above diverged_ratio x or diverged_drop_db below, or on a
// non-finite loss. A photometric loss saturates (a ruined KITTI run: 0.15 -> 0.4, 16.8 -> 9.4 dB),
// so the PSNR's drop is what usually says it. What resets the loss on purpose (the fine stage's
// start, an opacity reset) re-baselines both, with a grace period.
#pragma once

#include <cstdint>
#include <string>

namespace streetsim::train {

// What the guard has seen, kept with a checkpoint so that a resumed run is judged against the
// same best as before (a rollback resumes into the trouble it rolled back from).
struct DivergenceGuardState {
  bool started = false;
  int64_t baseline = 0;
  double mean = 0, best = 0, psnr_mean = 0, psnr_best = 0;
  // The training images' width it was seen at: a run that goes on at another resolution (low
  // resolution first) starts afresh, its PSNR is another scale's.
  int image_width = 0;
};

struct DivergenceGuardOptions {
  double mean_weight = 0.02;       // the running mean's weight per iteration (~50 iterations)
  double suspicious_ratio = 1.5, diverged_ratio = 3.0;
  double suspicious_drop_db = 2.5, diverged_drop_db = 5.0;
  int grace_iterations = 200;      // after a baseline: the mean settles, nothing is judged
};

class DivergenceGuard {
 public:
  enum class Verdict { kFine, kSuspicious, kDiverged };

  explicit DivergenceGuard(DivergenceGuardOptions options = {}) : options_(options) {}

  // The loss level changes on purpose here: judge from the next `grace_iterations` on.
  void Rebaseline(int64_t iteration);
  Verdict Observe(int64_t iteration, double loss, double psnr_db);

  DivergenceGuardState state(int image_width) const {
    return {started_, baseline_, mean_, best_, psnr_mean_, psnr_best_, image_width};
  }
  void Restore(const DivergenceGuardState& s);

  double mean() const { return mean_; }
  double best() const { return best_; }
  double psnr_mean() const { return psnr_mean_; }
  double psnr_best() const { return psnr_best_; }
  // Why the last verdict was not fine ("" when it was).
  const std::string& why() const { return why_; }

 private:
  DivergenceGuardOptions options_;
  int64_t baseline_ = 0;
  bool started_ = false;
  double mean_ = 0, best_ = 0;
  double psnr_mean_ = 0, psnr_best_ = 0;
  std::string why_;
};

}  // namespace streetsim::train
