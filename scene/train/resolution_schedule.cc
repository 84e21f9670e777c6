#include "scene/train/resolution_schedule.h"

#include <filesystem>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

absl::Status CheckLowResStage(const TrainOptions& opt) {
  if (!opt.low_res) return absl::OkStatus();
  const LowResStage& low = *opt.low_res;
  if (!(low.resolution_scale > 0 && low.resolution_scale < opt.resolution_scale)) {
    return absl::InvalidArgumentError(absl::StrCat("the low-resolution stage's scale (", low.resolution_scale,
                                                   ") must be above 0 and below the run's (", opt.resolution_scale,
                                                   ")"));
  }
  if (low.iterations < 1 || low.iterations >= opt.iterations) {
    return absl::InvalidArgumentError(absl::StrCat("the low-resolution stage's iterations (", low.iterations,
                                                   ") must be at least 1 and fewer than the run's (", opt.iterations,
                                                   ")"));
  }
  return absl::OkStatus();
}

absl::StatusOr<TrainResult> TrainInResolutionStages(const TrainOptions& opt, const std::string& out_dir,
                                                    const std::function<void(const Progress&)>& progress,
                                                    const TrainAtScale& train_at) {
  if (!opt.low_res) return train_at(opt, progress);
  if (absl::Status s = CheckLowResStage(opt); !s.ok()) return s;
  const LowResStage& low = *opt.low_res;
  int64_t resumed_at = 0;
  const std::string ckpt = (std::filesystem::path(out_dir) / "checkpoint.bin").string();
  if (opt.resume && std::filesystem::exists(ckpt)) {
    absl::StatusOr<int64_t> it = PeekCheckpointIteration(ckpt);
    if (!it.ok()) return it.status();
    resumed_at = *it;
  }
  double low_seconds = 0;
  if (resumed_at < low.iterations) {
    LOG(INFO) << "low-resolution stage: iterations " << resumed_at + 1 << "-" << low.iterations
              << " at resolution scale " << low.resolution_scale << ", then " << low.iterations + 1 << "-"
              << opt.iterations << " at " << opt.resolution_scale;
    TrainOptions stage = opt;
    stage.resolution_scale = low.resolution_scale;
    stage.iterations = static_cast<int>(low.iterations);
    stage.write_outputs = false;  // the run's outputs are the last stage's; this one ends in its checkpoint
    auto stage_progress = [&](const Progress& p) {
      if (!progress) return;
      Progress whole = p;
      whole.total = opt.iterations;
      whole.low_res_scale = low.resolution_scale;
      progress(whole);
    };
    absl::StatusOr<TrainResult> r = train_at(stage, stage_progress);
    if (!r.ok()) return r.status();
    if (r->iterations < low.iterations || (opt.stop_after > 0 && r->iterations >= opt.stop_after)) return r;
    low_seconds = r->seconds;
    LOG(INFO) << "iteration " << r->iterations << ": low-resolution stage done (" << r->gaussians << " Gaussians, "
              << r->seconds << " s); resolution scale " << opt.resolution_scale << " from here";
  }
  TrainOptions rest = opt;
  rest.resume = true;
  absl::StatusOr<TrainResult> r = train_at(rest, progress);
  // The run's time is both stages' (a resume counts from its own start, as a one-stage one does).
  if (r.ok() && low_seconds > 0) {
    r->seconds += low_seconds;
    // Time to 24 dB counts views at the run's resolution only (the low stage's are easier to fit).
    if (r->seconds_to_psnr24 >= 0) r->seconds_to_psnr24 += low_seconds;
  }
  return r;
}

}  // namespace streetsim::train
