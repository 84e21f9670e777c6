// Writing render outputs. Every write goes to a temporary file in the destination directory and
// is renamed into place, so a crash or a full disk never leaves a half-written image behind.
#pragma once

#include <string>
#include <vector>

#include "absl/status/status.h"

namespace streetsim {

// Linear RGB floats [H*W*3] -> 8-bit (clamped to [0,1] x 255, rounded). PNG or JPEG by extension.
absl::Status WriteRgb8(const std::string& path, int width, int height, const std::vector<float>& rgb);

// Single-channel float32 TIFF (.tif / .tiff).
absl::Status WriteFloatTiff(const std::string& path, int width, int height,
                            const std::vector<float>& values);

}  // namespace streetsim
