#include "scene/train/parts/pose_part.h"

#include <filesystem>

#include "render/common/log.h"
#include "scene/train/pose_refinement.h"

namespace streetsim::train {

absl::StatusOr<std::unique_ptr<PosePart>> PosePart::Create(bool asked, int num_views, const Hyper& h,
                                                           TrainState* st) {
  const bool refining = asked || !st->pose_delta.empty();
  if (refining) {
    if (!asked) {
      LOG(INFO) << "the checkpoint refines its camera poses: so does this run";
    }
    if (absl::Status s = PreparePoseCorrections(num_views, st); !s.ok()) return s;
    if (h.pose_refine_until > 0) {
      LOG(INFO) << "camera poses refined at iterations " << h.pose_refine_from + 1 << "-" << h.pose_refine_until;
    } else {
      LOG(INFO) << "camera poses refined from iteration " << h.pose_refine_from + 1 << " to the run's end";
    }
  }
  return std::unique_ptr<PosePart>(new PosePart(refining, h));
}

PinholeCamera PosePart::Camera(const View& view, int view_index, const TrainState& st) const {
  return refining_ ? CorrectedCamera(view.camera, ViewCorrection(st, view_index)) : view.camera;
}

absl::StatusOr<double> PosePart::AddGradients(const Iteration& i, TrainState* st, GaussianGrads* grads,
                                              ThreadPool& pool) {
  if (refining_ && i.it > h_.pose_refine_from && (h_.pose_refine_until == 0 || i.it <= h_.pose_refine_until)) {
    StepPoseCorrection(*i.rendered, *grads, *i.camera, i.view_index, h_, pool, st);
  }
  return 0.0;  // it reads the gradient, it adds none
}

absl::StatusOr<std::optional<std::vector<View>>> PosePart::Finish(const std::string& out_dir,
                                                                  const std::vector<View>& train_views,
                                                                  const TrainState& st,
                                                                  const std::vector<View>& heldout) const {
  if (!refining_) {
    std::error_code ec;
    std::filesystem::remove(std::filesystem::path(out_dir) / kPoseCorrectionsFileName, ec);  // not this run's
    return std::nullopt;
  }
  const std::vector<PoseCorrection> corrections = TrainedCorrections(train_views, st.pose_delta);
  if (absl::Status s = WritePoseCorrections(out_dir, corrections); !s.ok()) return s;
  LOG(INFO) << "pose corrections: " << CorrectionsSummary(corrections);
  std::vector<View> corrected = heldout;
  if (!corrected.empty()) ApplyPoseCorrections(corrections, &corrected);
  return corrected;
}

}  // namespace streetsim::train
