// PSNR* (method.md section 4): PSNR on the pixels of moving things. A pixel is dynamic when a
// LiDAR point of its frame that the init's dynamic-point mask (scene/init/dynamic_mask.h) flags
// projects into it, dilated by kDynamicDilatePx pixels (a (2r+1)^2 square) because the scan is
// sparse (64 beams: ~5 px between rows at 1242x375): the flagged points sample a moving object
// only along its beams. Occlusion between the LiDAR and the camera is ignored.
#pragma once

#include <cstdint>
#include <vector>

#include "absl/status/status.h"
#include "scene/log/drive_log.h"
#include "scene/train/dataset.h"

namespace streetsim::train {

inline constexpr int kDynamicDilatePx = 2;

// Fills View::dynamic_pixels of every view whose frame has a LiDAR scan and a neighbouring scan to
// judge it by (others stay empty). One
// mask computation per frame (it reads the frame's and its neighbours' scans).
absl::Status AttachDynamicPixels(const DriveLog& log, std::vector<View>* views, int dilate_px = kDynamicDilatePx);

// PSNR of `rendered` against `gt` ([W*H*3], values in [0, 1]) over the pixels where mask == want;
// -1 when there are none.
double MaskedPsnr(const float* rendered, const float* gt, const std::vector<uint8_t>& mask, uint8_t want);

}  // namespace streetsim::train
