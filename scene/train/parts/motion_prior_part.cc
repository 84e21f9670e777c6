#include "scene/train/parts/motion_prior_part.h"

#include <chrono>

#include <nlohmann/json.hpp>

#include "render/common/log.h"

namespace streetsim::train {

absl::StatusOr<std::unique_ptr<MotionPriorPart>> MotionPriorPart::Create(const MotionPriorOptions& options,
                                                                         const DriveLog* lidar_log,
                                                                         int holdout_every) {
  if (options.weight > 0 && lidar_log == nullptr) {
    return absl::FailedPreconditionError("the motion prior needs the log's LiDAR");
  }
  return std::unique_ptr<MotionPriorPart>(new MotionPriorPart(options, lidar_log, holdout_every));
}

absl::Status MotionPriorPart::Build(const TrainState& st, ThreadPool& pool) {
  const auto t0 = std::chrono::steady_clock::now();
  // Tracked in the training frames' scans only: held-out frames are never used.
  const DriveLog train_log =
      TrainingFramesLog(*lidar_log_, 0, static_cast<int>(lidar_log_->frames.size()), holdout_every_);
  absl::StatusOr<std::unique_ptr<MotionPrior>> mp = MotionPrior::Build(train_log, options_);
  if (!mp.ok() && !options_.optional) return mp.status();
  if (!mp.ok()) {
    LOG(WARNING) << "motion prior left out (the preset's; this log cannot carry it): " << mp.status().message();
    skipped_ = true;
    return absl::OkStatus();
  }
  prior_ = std::move(*mp);
  prior_->Assign(st.params.means.data(), st.size(), pool);
  rows_changed_ = false;
  LOG(INFO) << "motion prior: " << prior_->num_tracks() << " moving objects from " << train_log.frames.size()
            << " training frames' LiDAR ("
            << std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() << " s), weight "
            << options_.weight << ", " << MotionPriorScansName(options_.all_scans) << " scans; "
            << prior_->assigned() << " of " << st.size() << " Gaussians on moving objects";
  return absl::OkStatus();
}

absl::StatusOr<double> MotionPriorPart::AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                                     ThreadPool& pool) {
  if (!i.fine) return 0.0;
  if (options_.weight > 0 && !prior_ && !skipped_) {
    if (absl::Status s = Build(*st, pool); !s.ok()) return s;
  }
  if (!prior_) return 0.0;
  if (rows_changed_ || prior_->n() != st->size()) {
    prior_->Assign(st->params.means.data(), st->size(), pool);
    rows_changed_ = false;
  }
  grad_.assign(st->size() * 3, 0.0f);
  const double loss =
      prior_->AddGradient(i.view->time_us, st->params.means.data(), i.deformed_means->data(), grad_.data(), pool);
  for (size_t k = 0; k < grad_.size(); ++k) grads->means[k] += grad_[k];
  return loss;
}

void MotionPriorPart::AfterFieldBackward(const Iteration& i, GaussianGrads* grads) {
  // The identity path of Δx = deformed - canonical brought the prior's gradient into the
  // canonical means: it comes back out.
  if (!i.fine || !prior_) return;
  for (size_t k = 0; k < grad_.size(); ++k) grads->means[k] -= grad_[k];
}

void MotionPriorPart::Meta(nlohmann::json* meta) const {
  (*meta)["field_motion_prior"] = options_.weight;
  (*meta)["field_motion_prior_scans"] = MotionPriorScansName(options_.all_scans);
}

}  // namespace streetsim::train
