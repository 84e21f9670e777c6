// A training run's images for people: the loss / PSNR curve (DIR/curve.png) and the held-out
// previews (render | logged image, DIR/preview/). Written atomically (image_file.h) so that a
// viewer polling the run directory never reads half a PNG.
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/status.h"

namespace streetsim::train {

// Linear RGB floats (w x h x 3, row-major) to 8-bit RGB, clamped to [0, 1] and rounded.
cv::Mat ToRgb8(const std::vector<float>& rgb, int w, int h);

// The training curve (triples iteration, loss, training-view PSNR): loss on a log scale against
// the left axis, PSNR against the right; an RGB image. Fewer than two points: an empty plot.
cv::Mat PlotCurve(const std::vector<double>& curve);

// An 8-bit RGB image to a PNG at `path`, atomically.
absl::Status WriteRgbPng(const std::string& path, const cv::Mat& rgb8);

}  // namespace streetsim::train
