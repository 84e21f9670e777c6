#include "scene/train/parts/densification.h"

#include "render/common/log.h"

namespace streetsim::train {

DensifyEvents Densification::Step(int64_t it, int64_t stage_it, const GaussianGrads& grads, int width, int height,
                                  TrainState* st) const {
  DensifyEvents ev;
  // Not on the last iteration: nothing would repair the fresh clones / split children / reset
  // opacities before the scene is written and evaluated (3DGS's runs end long after densify_until).
  if (stage_it >= h_.densify_until || it >= iterations_) return ev;
  AccumulateStats(st, grads, width, height);
  if (stage_it > h_.densify_from && stage_it % h_.densify_interval == 0) {
    size_t added = 0, removed = 0;
    DensifyAndPrune(st, h_, stage_it, &added, &removed);
    LOG(INFO) << "iteration " << it << ": densified +" << added << " -" << removed << " -> " << st->size();
    ev.rows_changed = true;
  }
  const bool outputs_soon = outputs_at_end_ && iterations_ - it < h_.min_iterations_after_reset;
  if (stage_it % h_.opacity_reset_interval == 0 && !outputs_soon) {
    ResetOpacity(st);
    ev.opacity_reset = true;
  }
  return ev;
}

}  // namespace streetsim::train
