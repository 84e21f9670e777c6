#include "scene/train/parts/lidar_part.h"

#include "absl/strings/str_cat.h"

namespace streetsim::train {

absl::StatusOr<std::unique_ptr<LidarPart>> LidarPart::Create(const DriveLog& log, const LidarStageOptions& options) {
  absl::StatusOr<std::unique_ptr<LidarStage>> stage = LidarStage::Create(log, options);
  if (!stage.ok()) return stage.status();
  return std::unique_ptr<LidarPart>(new LidarPart(std::move(*stage)));
}

absl::StatusOr<double> LidarPart::AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                               ThreadPool&) {
  return stage_->Step(st, i.view->frame, i.it, grads, i.deformed_means);
}

std::string LidarPart::Summary() const {
  if (stage_->steps() == 0) return {};
  return absl::StrCat("LiDAR step: ", stage_->steps(), " steps, ", stage_->total_ms() / stage_->steps(), " ms each");
}

}  // namespace streetsim::train
