// Evaluation metrics as JSON: the one format of `streetsim eval`'s output and of the held-out
// metrics a training run leaves beside its scene (DIR/heldout.json), so that scripts and the
// server read one schema. A metric that does not apply (no LiDAR, no dynamic pixel) is null.
#pragma once

#include <string>

#include <nlohmann/json.hpp>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "scene/eval/evaluate.h"

namespace streetsim::train {

inline constexpr char kHeldoutMetricsFileName[] = "heldout.json";

// A metric that may not apply (negative: not measured) as JSON: the value, or null.
nlohmann::json MetricOrNull(double v);

// {"psnr", "ssim", "depth_median_abs_m", "depth_within_5pct", "psnr_dynamic", "psnr_static"}.
nlohmann::json FrameMetricsJson(const FrameMetrics& m);

// {"views": N, "frames": [{"name", "frame", metrics...}], "mean": {metrics...}}.
nlohmann::json EvalResultJson(const EvalResult& r);

// DIR/heldout.json, atomically.
absl::Status WriteHeldoutMetrics(const std::string& dir, const EvalResult& heldout);

// DIR/heldout.json back (per-frame metrics; null -> -1; the mean as written). NotFound without
// the file, DataLoss naming it when it is not that schema.
absl::StatusOr<EvalResult> ReadHeldoutMetrics(const std::string& dir);

}  // namespace streetsim::train
