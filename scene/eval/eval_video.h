// The video of `streetsim eval --video PATH` (docs/training.md "Eval outputs"): the evaluated
// views of one camera in time order, each frame its panels side by side (rendered | ground truth
// [| dynamic Gaussians only]), written with OpenCV's VideoWriter.
//
// Containers and codecs (Debian bookworm's OpenCV 4.6 has the FFmpeg and its own MJPEG writers):
//   .avi: MJPG through FFmpeg, else OpenCV's built-in MJPEG writer (needs no library, always works);
//   .mp4: H.264 ('avc1'), else MPEG-4 part 2 ('mp4v'); neither: an error that suggests .avi.
// Frames are padded to even sizes (H.264 needs them). The file is written under a temporary name
// in the target directory and renamed into place, so a failure never leaves a partial video.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "absl/status/statusor.h"

namespace streetsim::train {

// Checks what can be checked before the evaluation runs: the extension (.avi or .mp4, any case)
// and that the directory exists (InvalidArgument / NotFound).
absl::Status CheckVideoPath(const std::string& path);

// Frames per second from frame times: 1e6 / the median spacing of the distinct sorted times;
// 10 when there are fewer than two distinct times.
double FpsFromTimes(std::vector<int64_t> times_us);

// The panels (CV_8UC3, R G B order) side by side at the first panel's height (others resized),
// each labelled in its top-left corner when wide enough (>= 160 px).
cv::Mat SideBySide(const std::vector<cv::Mat>& panels_rgb, const std::vector<std::string>& labels);

struct VideoSummary {
  std::string path;
  std::string codec;  // FourCC used, e.g. "MJPG", "avc1"
  std::string backend;  // OpenCV's writer backend, e.g. "FFMPEG", "CV_MJPEG"
  int frames = 0;
  int width = 0, height = 0;
  double fps = 0;
};

// Writes `frames_rgb` (CV_8UC3, R G B; resized to the first frame's size when they differ) to
// `path` in the given order. FailedPrecondition when no writer for the container opens.
absl::StatusOr<VideoSummary> WriteVideo(const std::string& path, const std::vector<cv::Mat>& frames_rgb, double fps);

// Collects the eval's frames (in any order) and writes them sorted by time. Frames wait as
// losslessly compressed PNG in memory (about 5x smaller than raw: a 3-panel 1242x375 frame is
// ~0.8 MB instead of 4.2 MB; ~0.1 s to encode on the shared cores).
class EvalVideo {
 public:
  // fps <= 0: from the frames' times (FpsFromTimes).
  EvalVideo(std::string path, double fps) : path_(std::move(path)), fps_(fps) {}
  // One evaluated view: `camera` names its camera (the video keeps the first camera it is given;
  // views of other cameras are skipped); `panels_rgb` as for SideBySide.
  absl::Status Add(int64_t time_us, const std::string& camera, const std::vector<cv::Mat>& panels_rgb,
                   const std::vector<std::string>& labels);
  absl::StatusOr<VideoSummary> Write() const;
  size_t size() const { return frames_.size(); }

 private:
  struct Frame {
    int64_t time_us;
    size_t order;
    std::vector<uint8_t> png;  // the side-by-side frame, B G R
  };
  std::string path_;
  double fps_;
  std::string camera_;
  std::vector<Frame> frames_;
};

}  // namespace streetsim::train
