// Training / evaluation views of a DriveLog: every camera observation of every frame, its image
// (undistorted for COLMAP cameras and cropped to the pixels that come from the source image,
// resized to the resolution scale) and its sparse LiDAR depth
// samples, split by the held-out protocol (every K-th frame: frames K-1, 2K-1, ...).
#pragma once

#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"
#include "render/camera.h"
#include "scene/log/drive_log.h"
#include "scene/train/losses.h"

namespace streetsim::train {

struct View {
  int frame = 0;  // index into DriveLog::frames
  int camera_obs = 0;
  int64_t time_us = 0;  // the frame's time (the dynamic field's time axis)
  std::string name;
  PinholeCamera camera;  // at the resolution scale
  cv::Mat rgb8;          // CV_8UC3, R G B, camera.width x camera.height
  // A grayscale camera's view in a log that has colour cameras: trained and measured on the
  // render's luminance (losses.h LuminanceRgb), so that one surface is not taught two colours.
  bool luminance_only = false;
  std::vector<DepthSample> lidar;  // sparse depth (nearest wins per scaled pixel)
  // PSNR* (scene/train/dynamic_pixels.h): 1 = pixel of a moving LiDAR point [W*H]; empty = unknown.
  std::vector<uint8_t> dynamic_pixels;
  // Linear RGB floats [H*W*3] in [0,1].
  std::vector<float> RgbFloat() const;
};

enum class Split { kTrain, kTest, kAll };

// Frame f is held out when holdout_every > 0 and f % holdout_every == holdout_every - 1.
bool IsHeldOut(int frame, int holdout_every);

// A copy of `log` with only frames [first_frame, end_frame) that are not held out: what scene init
// and the motion prior may see.
DriveLog TrainingFramesLog(const DriveLog& log, int first_frame, int end_frame, int holdout_every);

// What a grayscale camera does in a log that also has colour cameras (docs/training.md
// "Grayscale cameras"). In a log of grayscale cameras only, they train as they are (the scene
// is gray, as every view it is measured on).
enum class GrayscaleCameras { kLuminance, kSkip, kAsColour };

struct DatasetOptions {
  GrayscaleCameras grayscale = GrayscaleCameras::kLuminance;
  double resolution_scale = 1.0;
  int holdout_every = 4;
  Split split = Split::kTrain;
  bool load_depth = true;
};

absl::StatusOr<std::vector<View>> LoadViews(const DriveLog& log, const DatasetOptions& options);

// The pinhole camera of an observation at a resolution scale (OpenCV pixel-centre convention).
PinholeCamera ScaledCamera(const DriveLog& log, int frame, int camera_obs, double scale);

}  // namespace streetsim::train
