// The appearance terms between the render and the photometric loss (docs/training.md "Sky and
// exposure"): a per-image affine colour (exposure: out = A rgb + b, 12 numbers per training
// view) and the learned sky (the background colour seen through each pixel's remaining
// transmittance). Each has its own small Adam (Hyper's exposure_lr / sky_lr, TrainState's aux
// step), stepped once per iteration from the loss's image gradient.
#pragma once

#include <vector>

#include <Eigen/Core>

#include "render/engine.h"
#include "scene/train/dataset.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

class Appearance {
 public:
  Appearance(bool exposure, bool sky, const Hyper& h) : exposure_(exposure), sky_(sky), h_(h) {}

  // A new run's sky: the mean colour of the training images' top tenth.
  void InitSky(const std::vector<View>& views, TrainState* st) const;
  // The render's background (black without a learned sky).
  Eigen::Vector3f Background(const TrainState& st) const;

  // The image the loss compares for training view `view`: the render's, or its exposure's.
  const std::vector<float>& Apply(const TrainState& st, int view, const RenderOutput& out);
  // From dL/d(Apply's image): steps the exposure of `view` and the sky, and returns dL/d(render).
  const std::vector<float>& Backward(TrainState* st, int view, const RenderOutput& out,
                                     const std::vector<float>& d_image);

 private:
  bool exposure_, sky_;
  Hyper h_;
  std::vector<float> exposed_, d_render_;
};

}  // namespace streetsim::train
