#include "scene/train/train_outputs.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <string>

#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "scene/train/image_file.h"

namespace streetsim::train {

cv::Mat ToRgb8(const std::vector<float>& rgb, int w, int h) {
  cv::Mat m(h, w, CV_8UC3);
  for (int y = 0; y < h; ++y) {
    uint8_t* row = m.ptr<uint8_t>(y);
    for (int i = 0; i < w * 3; ++i) {
      const float v = rgb[static_cast<size_t>(y) * w * 3 + i];
      row[i] = static_cast<uint8_t>(std::lround(std::min(std::max(v, 0.0f), 1.0f) * 255.0f));
    }
  }
  return m;
}

// Loss (log scale, left axis) and PSNR (right axis) against iteration.
cv::Mat PlotCurve(const std::vector<double>& curve) {
  const int W = 900, H = 420, L = 70, R = 70, T = 30, B = 50;
  cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
  const size_t n = curve.size() / 3;
  if (n < 2) return img;
  double it_max = curve[(n - 1) * 3], lmin = 1e9, lmax = -1e9, pmin = 1e9, pmax = -1e9;
  for (size_t i = 0; i < n; ++i) {
    const double l = std::log10(std::max(curve[i * 3 + 1], 1e-6));
    lmin = std::min(lmin, l), lmax = std::max(lmax, l);
    pmin = std::min(pmin, curve[i * 3 + 2]), pmax = std::max(pmax, curve[i * 3 + 2]);
  }
  if (lmax - lmin < 1e-3) lmax = lmin + 1;
  if (pmax - pmin < 1e-3) pmax = pmin + 1;
  auto px = [&](double it) { return L + static_cast<int>((W - L - R) * it / std::max(it_max, 1.0)); };
  auto py = [&](double v, double lo, double hi) { return T + static_cast<int>((H - T - B) * (1 - (v - lo) / (hi - lo))); };
  cv::rectangle(img, {L, T}, {W - R, H - B}, cv::Scalar(0, 0, 0));
  for (size_t i = 1; i < n; ++i) {
    const double l0 = std::log10(std::max(curve[(i - 1) * 3 + 1], 1e-6)), l1 = std::log10(std::max(curve[i * 3 + 1], 1e-6));
    cv::line(img, {px(curve[(i - 1) * 3]), py(l0, lmin, lmax)}, {px(curve[i * 3]), py(l1, lmin, lmax)}, cv::Scalar(200, 60, 30), 1);
    cv::line(img, {px(curve[(i - 1) * 3]), py(curve[(i - 1) * 3 + 2], pmin, pmax)},
             {px(curve[i * 3]), py(curve[i * 3 + 2], pmin, pmax)}, cv::Scalar(30, 60, 200), 1);
  }
  auto text = [&](const std::string& s, int x, int y, cv::Scalar c) {
    cv::putText(img, s, {x, y}, cv::FONT_HERSHEY_SIMPLEX, 0.45, c, 1);
  };
  text(absl::StrCat("loss ", std::to_string(std::pow(10, lmax)).substr(0, 6)), 5, T + 10, cv::Scalar(200, 60, 30));
  text(std::to_string(std::pow(10, lmin)).substr(0, 6), 5, H - B, cv::Scalar(200, 60, 30));
  text(absl::StrCat(std::to_string(pmax).substr(0, 5), " dB"), W - R + 3, T + 10, cv::Scalar(30, 60, 200));
  text(absl::StrCat(std::to_string(pmin).substr(0, 5), " dB"), W - R + 3, H - B, cv::Scalar(30, 60, 200));
  text(absl::StrCat("iteration 0 .. ", static_cast<int64_t>(it_max),
                    "   (red: loss, log scale; blue: training-view PSNR, 50-view mean)"), L, H - 15, cv::Scalar(0, 0, 0));
  // The plot was drawn in RGB order.
  return img;
}

absl::Status WriteRgbPng(const std::string& path, const cv::Mat& rgb8) {
  cv::Mat bgr;
  cv::cvtColor(rgb8, bgr, cv::COLOR_RGB2BGR);
  return WriteImageAtomic(path, bgr);
}

}  // namespace streetsim::train
