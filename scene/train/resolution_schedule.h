// Training from low to full resolution: a run's first iterations at a fraction of its resolution,
// the rest at its own (TrainOptions::low_res, `streetsim train --low-res-scale S
// --low-res-iterations N`; docs/training.md "Low resolution first"). Not S3Gaussian's "coarse
// stage", which is the static warm-up (either stage can be at low resolution). A fine-stage
// iteration at a quarter of the pixels costs a fraction of a full one, and the Gaussians and the
// field are 3D, so what the low-resolution stage learns carries over; the last stage has to be at
// the run's resolution, as Gaussians fitted to a quarter of the pixels alias when rendered at four
// times as many.
//
// The switch is a checkpoint: the low-resolution stage ends with one at its last iteration and the
// rest of the run resumes from it at the run's resolution, so a run killed in either stage
// continues with --resume (config.json records the stage, and a resume keeps it).
#pragma once

#include <functional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "scene/train/trainer.h"

namespace streetsim::train {

// InvalidArgument unless options.low_res is unset or names a scale below the run's and a stage
// that ends before the run does.
absl::Status CheckLowResStage(const TrainOptions& options);

// Trains the views of one resolution: `stage` is the run's options with resolution_scale,
// iterations, resume and write_outputs set for the stage (stage.low_res is the run's, for its
// train_meta.json).
using TrainAtScale = std::function<absl::StatusOr<TrainResult>(const TrainOptions& stage,
                                                                const std::function<void(const Progress&)>& progress)>;

// Without options.low_res: train_at(options). With it: the low-resolution stage (iterations up to
// low_res->iterations at low_res->resolution_scale, no outputs but its checkpoint) unless out_dir's
// checkpoint is already at or past its end, then the rest of the run resumed from that checkpoint
// at options.resolution_scale. Progress reports count against the whole run, and so does the
// result's seconds (seconds_to_psnr24: views at the run's resolution only). A stage that stops
// early (cancelled, failed, TrainOptions::stop_after) ends the run there.
absl::StatusOr<TrainResult> TrainInResolutionStages(const TrainOptions& options, const std::string& out_dir,
                                                    const std::function<void(const Progress&)>& progress,
                                                    const TrainAtScale& train_at);

}  // namespace streetsim::train
