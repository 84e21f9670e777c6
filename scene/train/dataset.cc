#include "scene/train/dataset.h"

#include <algorithm>
#include <cmath>
#include <filesystem>

#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "scene/init/depth_maps.h"
#include "scene/log/undistort.h"

namespace streetsim::train {

std::vector<float> View::RgbFloat() const {
  std::vector<float> out(static_cast<size_t>(rgb8.rows) * rgb8.cols * 3);
  for (int v = 0; v < rgb8.rows; ++v) {
    const uint8_t* row = rgb8.ptr<uint8_t>(v);
    float* dst = out.data() + static_cast<size_t>(v) * rgb8.cols * 3;
    for (int i = 0; i < rgb8.cols * 3; ++i) dst[i] = row[i] * (1.0f / 255.0f);
  }
  return out;
}

bool IsHeldOut(int frame, int holdout_every) {
  return holdout_every > 0 && frame % holdout_every == holdout_every - 1;
}

DriveLog TrainingFramesLog(const DriveLog& log, int first_frame, int end_frame, int holdout_every) {
  DriveLog train_log = log;
  train_log.frames.clear();
  for (int f = first_frame; f < end_frame; ++f)
    if (!IsHeldOut(f, holdout_every)) train_log.frames.push_back(log.frames[f]);
  return train_log;
}

namespace {

// k: the pinhole intrinsics the view's image has after undistortion and cropping (CroppedPinhole).
PinholeCamera ScaledPinhole(const DriveLog& log, int frame, int camera_obs, const CameraIntrinsics& k, double scale) {
  const CameraObservation& obs = log.frames[frame].cameras[camera_obs];
  PinholeCamera cam;
  cam.width = std::max(1, static_cast<int>(std::lround(k.width * scale)));
  cam.height = std::max(1, static_cast<int>(std::lround(k.height * scale)));
  const double sx = static_cast<double>(cam.width) / k.width, sy = static_cast<double>(cam.height) / k.height;
  cam.fx = k.fx * sx;
  cam.fy = k.fy * sy;
  cam.cx = (k.cx + 0.5) * sx - 0.5;
  cam.cy = (k.cy + 0.5) * sy - 0.5;
  cam.T_world_from_cam = WorldFromCamera(log, log.frames[frame], obs);
  return cam;
}

}  // namespace

PinholeCamera ScaledCamera(const DriveLog& log, int frame, int camera_obs, double scale) {
  const CameraObservation& obs = log.frames[frame].cameras[camera_obs];
  return ScaledPinhole(log, frame, camera_obs, CroppedPinhole(log.cameras[obs.camera].intrinsics), scale);
}

absl::StatusOr<std::vector<View>> LoadViews(const DriveLog& log, const DatasetOptions& options) {
  if (!(options.resolution_scale > 0 && options.resolution_scale <= 1)) {
    return absl::InvalidArgumentError("resolution scale must be in (0, 1]");
  }
  std::vector<View> views;
  // Per camera: the crop that removes undistortion's black border, and the resulting pinhole.
  std::vector<cv::Rect> crop(log.cameras.size());
  std::vector<CameraIntrinsics> cropped(log.cameras.size());
  for (size_t c = 0; c < log.cameras.size(); ++c) {
    crop[c] = ValidUndistortedRect(log.cameras[c].intrinsics);
    cropped[c] = CroppedPinhole(log.cameras[c].intrinsics);
    if (crop[c].width < 1 || crop[c].height < 1) {
      return absl::InvalidArgumentError(absl::StrCat("camera ", log.cameras[c].name,
                                                     ": no pixel of the undistorted image comes from the source"));
    }
  }
  bool rig_has_colour = false;
  for (const CameraSensor& c : log.cameras) rig_has_colour = rig_has_colour || c.colour;
  for (int f = 0; f < static_cast<int>(log.frames.size()); ++f) {
    const bool held = IsHeldOut(f, options.holdout_every);
    if (options.split == Split::kTrain && held) continue;
    if (options.split == Split::kTest && !held) continue;
    for (int c = 0; c < static_cast<int>(log.frames[f].cameras.size()); ++c) {
      const CameraObservation& obs = log.frames[f].cameras[c];
      const CameraIntrinsics& k = log.cameras[obs.camera].intrinsics;
      const bool gray_beside_colour = rig_has_colour && !log.cameras[obs.camera].colour;
      if (gray_beside_colour && options.grayscale == GrayscaleCameras::kSkip) continue;
      View v;
      v.luminance_only = gray_beside_colour && options.grayscale == GrayscaleCameras::kLuminance;
      v.frame = f;
      v.camera_obs = c;
      v.time_us = log.frames[f].time_us;
      v.name = absl::StrCat(log.cameras[obs.camera].name, "/", std::filesystem::path(obs.path).filename().string());
      v.camera = ScaledPinhole(log, f, c, cropped[obs.camera], options.resolution_scale);
      absl::StatusOr<cv::Mat> img = LoadImageRgb(obs.path);
      if (!img.ok()) return img.status();
      if (img->cols != k.width || img->rows != k.height) {
        return absl::InvalidArgumentError(absl::StrCat(obs.path, ": image is ", img->cols, "x", img->rows,
                                                       ", the camera says ", k.width, "x", k.height));
      }
      if (!k.IsPinhole()) {
        absl::StatusOr<cv::Mat> u = UndistortImage(*img, k);
        if (!u.ok()) return u.status();
        *img = (*u)(crop[obs.camera]).clone();
      }
      if (v.camera.width != img->cols || v.camera.height != img->rows) {
        cv::resize(*img, v.rgb8, cv::Size(v.camera.width, v.camera.height), 0, 0, cv::INTER_AREA);
      } else {
        v.rgb8 = *img;
      }
      if (options.load_depth && !log.frames[f].lidars.empty()) {
        absl::StatusOr<cv::Mat> d = SparseDepthMap(log, f, c);
        if (!d.ok()) return d.status();
        // Nearest wins within each scaled pixel.
        std::vector<float> best(static_cast<size_t>(v.camera.width) * v.camera.height, 0.0f);
        const cv::Rect& r = crop[obs.camera];
        const double sx = static_cast<double>(v.camera.width) / r.width, sy = static_cast<double>(v.camera.height) / r.height;
        for (int y = r.y; y < std::min(d->rows, r.y + r.height); ++y) {
          const float* row = d->ptr<float>(y);
          for (int x = r.x; x < std::min(d->cols, r.x + r.width); ++x) {
            if (!(row[x] > 0)) continue;
            const int u = std::min(v.camera.width - 1, static_cast<int>((x - r.x + 0.5) * sx));
            const int w = std::min(v.camera.height - 1, static_cast<int>((y - r.y + 0.5) * sy));
            float& b = best[static_cast<size_t>(w) * v.camera.width + u];
            if (b == 0 || row[x] < b) b = row[x];
          }
        }
        for (size_t i = 0; i < best.size(); ++i)
          if (best[i] > 0) v.lidar.push_back({static_cast<uint32_t>(i), best[i]});
      }
      views.push_back(std::move(v));
    }
  }
  return views;
}

}  // namespace streetsim::train
