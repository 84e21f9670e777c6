// LiDAR supervision (lidar_stage.h, docs/training.md "LiDAR losses") as a part: on every stage,
// on every k-th iteration, the frame's scan against the rendered range image. In the fine stage
// it renders the deformed means, and its means gradient joins the camera's before the field's
// backward.
#pragma once

#include <memory>

#include "scene/log/drive_log.h"
#include "scene/train/lidar_stage.h"
#include "scene/train/parts/iteration_part.h"

namespace streetsim::train {

class LidarPart : public IterationPart {
 public:
  // `log` must outlive the part.
  static absl::StatusOr<std::unique_ptr<LidarPart>> Create(const DriveLog& log, const LidarStageOptions& options);

  absl::StatusOr<double> AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                      ThreadPool& pool) override;
  std::string Summary() const override;

 private:
  explicit LidarPart(std::unique_ptr<LidarStage> stage) : stage_(std::move(stage)) {}
  std::unique_ptr<LidarStage> stage_;
};

}  // namespace streetsim::train
