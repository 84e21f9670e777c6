// Image files written atomically: to a temporary file beside the target, then renamed into place,
// so that a reader (or a killed run) never sees a partial image. Used by the eval outputs
// (decomposition.h) and the CLI's render outputs (client/cli/image_io.h).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/status.h"

namespace streetsim::train {

// `image` as OpenCV stores it (BGR order for colour) to `path`, the encoder chosen by the path's
// extension, with cv::imwrite `params`. NotFound when the directory does not exist.
absl::Status WriteImageAtomic(const std::string& path, const cv::Mat& image, const std::vector<int>& params = {});

}  // namespace streetsim::train
