// What a training job's stages leave in its work directory, read for the job record: the
// Gaussian count, the held-out metrics, whether the trainer can resume, the preview image. The
// job runner (job_runner.h) runs the stages; this module only reads their files.
#pragma once

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "scene/train/trainer.h"
#include "streetsim/v1/training.pb.h"

namespace streetsim::server {

// "element vertex N" from a PLY header; 0 if unreadable.
uint64_t PlyVertexCount(const std::string& path);

// The trained scene's Gaussians: WORK/scene.ply, or a clip set's clips together (WORK/scene.ply
// is then init's).
uint64_t TrainedGaussianCount(const std::string& work);

// The trained scene's held-out metrics (the trainer's WORK/heldout.json; a clip set: its clips'
// merged); views = 0 when none. A damaged file is logged and reported as none: the scene is fine.
v1::HeldOutMetrics TrainedHeldoutMetrics(const std::string& work);

// The scene's train_meta.json (train::ReadSceneMeta: field, iterations ...; a clip set: its first
// clip's, every clip trains with the same options).
absl::StatusOr<train::SceneMeta> TrainedSceneMeta(const std::string& work);

// The trainer checkpoints in WORK, or in WORK/clip_KKK for a clip set; either one resumes.
bool HasTrainerCheckpoint(const std::string& work);

// The first held-out preview the trainer wrote (WORK/preview/*.png, render | ground truth),
// scaled down to 384 px wide and re-encoded as PNG (job records, and ListJobs, carry it); "" if none.
std::string FirstPreviewPng(const std::string& work);

}  // namespace streetsim::server
