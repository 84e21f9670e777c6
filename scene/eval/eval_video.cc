#include "scene/eval/eval_video.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace streetsim::train {
namespace {

std::string LowerExtension(const std::string& path) {
  return absl::AsciiStrToLower(std::filesystem::path(path).extension().string());
}

struct Candidate {
  int api;
  char fourcc[5];
};

// In order of preference per container (see the header).
std::vector<Candidate> CandidatesFor(const std::string& ext) {
  if (ext == ".avi") return {{cv::CAP_FFMPEG, "MJPG"}, {cv::CAP_OPENCV_MJPEG, "MJPG"}};
  return {{cv::CAP_FFMPEG, "avc1"}, {cv::CAP_FFMPEG, "mp4v"}, {cv::CAP_ANY, "mp4v"}};
}

cv::Mat EvenSized(const cv::Mat& m) {
  const int pad_x = m.cols % 2, pad_y = m.rows % 2;
  if (!pad_x && !pad_y) return m;
  cv::Mat out;
  cv::copyMakeBorder(m, out, 0, pad_y, 0, pad_x, cv::BORDER_CONSTANT, cv::Scalar(0, 0, 0));
  return out;
}

}  // namespace

absl::Status CheckVideoPath(const std::string& path) {
  const std::filesystem::path target(path);
  const std::string ext = LowerExtension(path);
  if (ext != ".avi" && ext != ".mp4") {
    return absl::InvalidArgumentError(absl::StrCat("--video ", path, ": the file must end in .avi or .mp4"));
  }
  std::error_code ec;
  if (std::filesystem::is_directory(target, ec)) {
    return absl::InvalidArgumentError(absl::StrCat("--video ", path, ": is a directory"));
  }
  const std::filesystem::path dir = target.has_parent_path() ? target.parent_path() : ".";
  if (!std::filesystem::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat("--video ", path, ": directory ", dir.string(), " does not exist"));
  }
  return absl::OkStatus();
}

double FpsFromTimes(std::vector<int64_t> times_us) {
  std::sort(times_us.begin(), times_us.end());
  times_us.erase(std::unique(times_us.begin(), times_us.end()), times_us.end());
  if (times_us.size() < 2) return 10.0;
  std::vector<int64_t> dt(times_us.size() - 1);
  for (size_t i = 0; i + 1 < times_us.size(); ++i) dt[i] = times_us[i + 1] - times_us[i];
  std::nth_element(dt.begin(), dt.begin() + dt.size() / 2, dt.end());
  return 1e6 / static_cast<double>(dt[dt.size() / 2]);
}

cv::Mat SideBySide(const std::vector<cv::Mat>& panels, const std::vector<std::string>& labels) {
  if (panels.empty()) return cv::Mat();
  const int h = panels[0].rows;
  std::vector<cv::Mat> row;
  for (size_t i = 0; i < panels.size(); ++i) {
    cv::Mat p = panels[i];
    if (p.rows != h) cv::resize(p, p, cv::Size(std::max(1, p.cols * h / std::max(1, p.rows)), h), 0, 0, cv::INTER_AREA);
    else p = p.clone();
    if (i < labels.size() && p.cols >= 160 && h >= 24) {
      const double scale = std::clamp(p.cols / 800.0, 0.35, 1.0);
      const cv::Point at(4, 4 + static_cast<int>(std::lround(14 * scale)));
      cv::putText(p, labels[i], at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(0, 0, 0), 3, cv::LINE_AA);
      cv::putText(p, labels[i], at, cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(255, 255, 255), 1, cv::LINE_AA);
    }
    row.push_back(p);
  }
  cv::Mat out;
  cv::hconcat(row, out);
  return out;
}

absl::StatusOr<VideoSummary> WriteVideo(const std::string& path, const std::vector<cv::Mat>& frames, double fps) {
  if (absl::Status s = CheckVideoPath(path); !s.ok()) return s;
  if (frames.empty() || frames[0].empty()) return absl::InvalidArgumentError(absl::StrCat(path, ": no frames"));
  if (!(fps > 0) || !std::isfinite(fps)) return absl::InvalidArgumentError(absl::StrCat(path, ": fps ", fps));
  const std::filesystem::path target(path);
  const std::filesystem::path dir = target.has_parent_path() ? target.parent_path() : ".";
  const std::string ext = LowerExtension(path);
  const std::filesystem::path tmp = dir / absl::StrCat(".", target.stem().string(), ".tmp", getpid(), ext);
  const cv::Mat first = EvenSized(frames[0]);
  VideoSummary summary;
  summary.path = path;
  summary.width = first.cols;
  summary.height = first.rows;
  std::error_code ec;
  cv::VideoWriter writer;
  std::vector<std::string> tried;
  for (const Candidate& c : CandidatesFor(ext)) {
    // OpenCV's own MJPEG writer takes whole frame rates >= 1 only.
    const double use_fps = c.api == cv::CAP_OPENCV_MJPEG ? std::max(1.0, std::round(fps)) : fps;
    const int fourcc = cv::VideoWriter::fourcc(c.fourcc[0], c.fourcc[1], c.fourcc[2], c.fourcc[3]);
    bool opened = false;
    try {
      opened = writer.open(tmp.string(), c.api, fourcc, use_fps, first.size(), true);
    } catch (const cv::Exception&) {
      opened = false;
    }
    if (opened) {
      summary.codec = c.fourcc;
      summary.backend = writer.getBackendName();
      summary.fps = use_fps;
      break;
    }
    tried.push_back(c.fourcc);
    std::filesystem::remove(tmp, ec);
  }
  if (!writer.isOpened()) {
    return absl::FailedPreconditionError(absl::StrCat(path, ": no video writer opens for ", ext, " (tried ",
                                                      absl::StrJoin(tried, ", "), ")",
                                                      ext == ".mp4" ? "; write an .avi (MJPG) instead" : ""));
  }
  cv::Mat bgr;
  for (const cv::Mat& f : frames) {
    cv::Mat sized = f;
    if (f.cols != frames[0].cols || f.rows != frames[0].rows) cv::resize(f, sized, frames[0].size(), 0, 0, cv::INTER_AREA);
    cv::cvtColor(EvenSized(sized), bgr, cv::COLOR_RGB2BGR);
    writer.write(bgr);
    ++summary.frames;
  }
  writer.release();
  if (std::filesystem::file_size(tmp, ec) == 0 || ec) {
    std::filesystem::remove(tmp, ec);
    return absl::InternalError(absl::StrCat(path, ": the ", summary.codec, " writer wrote nothing"));
  }
  std::filesystem::rename(tmp, target, ec);
  if (ec) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place: ", ec.message()));
  }
  return summary;
}

absl::Status EvalVideo::Add(int64_t time_us, const std::string& camera, const std::vector<cv::Mat>& panels,
                            const std::vector<std::string>& labels) {
  if (frames_.empty()) camera_ = camera;
  if (camera != camera_) return absl::OkStatus();
  cv::Mat bgr;
  cv::cvtColor(SideBySide(panels, labels), bgr, cv::COLOR_RGB2BGR);
  Frame f{time_us, frames_.size(), {}};
  if (!cv::imencode(".png", bgr, f.png, {cv::IMWRITE_PNG_COMPRESSION, 1})) {
    return absl::InternalError("eval video: cannot encode a frame");
  }
  frames_.push_back(std::move(f));
  return absl::OkStatus();
}

absl::StatusOr<VideoSummary> EvalVideo::Write() const {
  std::vector<const Frame*> order;
  for (const Frame& f : frames_) order.push_back(&f);
  std::sort(order.begin(), order.end(), [](const Frame* a, const Frame* b) {
    return a->time_us != b->time_us ? a->time_us < b->time_us : a->order < b->order;
  });
  std::vector<cv::Mat> mats;
  std::vector<int64_t> times;
  for (const Frame* f : order) {
    cv::Mat rgb;
    cv::cvtColor(cv::imdecode(f->png, cv::IMREAD_COLOR), rgb, cv::COLOR_BGR2RGB);
    mats.push_back(std::move(rgb));
    times.push_back(f->time_us);
  }
  return WriteVideo(path_, mats, fps_ > 0 ? fps_ : FpsFromTimes(times));
}

}  // namespace streetsim::train
