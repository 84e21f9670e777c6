#include "scene/train/stage_history.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "scene/common/checked_file.h"
#include "scene/train/train_outputs.h"

namespace streetsim::train {

absl::StatusOr<std::vector<StagePoint>> ReadStageHistory(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kStageHistoryFile).string();
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("no ", path));
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  if (!j.is_object() || !j.contains("stages") || !j["stages"].is_array()) {
    return absl::DataLossError(absl::StrCat(path, " is damaged"));
  }
  std::vector<StagePoint> out;
  for (const nlohmann::json& s : j["stages"]) {
    if (!s.is_object() || !s.contains("iteration") || !s["iteration"].is_number_integer() ||
        !s.contains("seconds") || !s["seconds"].is_number() || !s.contains("psnr") || !s["psnr"].is_number() ||
        !s.contains("ssim") || !s["ssim"].is_number()) {
      return absl::DataLossError(absl::StrCat(path, " is damaged (a stage without iteration, seconds, psnr, ssim)"));
    }
    out.push_back({s["iteration"].get<int64_t>(), s["seconds"].get<double>(), s["psnr"].get<double>(),
                   s["ssim"].get<double>()});
  }
  return out;
}

absl::Status AppendStagePoint(const std::string& dir, int64_t iteration, double seconds, double psnr, double ssim) {
  absl::StatusOr<std::vector<StagePoint>> read = ReadStageHistory(dir);
  // A damaged history is a record, not the run: it starts again rather than stopping training.
  std::vector<StagePoint> points = read.ok() ? *read : std::vector<StagePoint>{};
  points.erase(std::remove_if(points.begin(), points.end(), [&](const StagePoint& p) { return p.iteration >= iteration; }),
               points.end());
  const double before = points.empty() ? 0 : points.back().seconds;
  points.push_back({iteration, before + seconds, psnr, ssim});
  nlohmann::json j;
  j["stages"] = nlohmann::json::array();
  for (const StagePoint& p : points) {
    j["stages"].push_back({{"iteration", p.iteration}, {"seconds", p.seconds}, {"psnr", p.psnr}, {"ssim", p.ssim}});
  }
  const std::filesystem::path d(dir);
  if (absl::Status s = checked_file::WriteAtomically((d / kStageHistoryFile).string(), j.dump(2) + "\n"); !s.ok()) {
    return s;
  }
  return WriteRgbPng((d / "heldout_curve.png").string(), PlotStageHistory(points));
}

cv::Mat PlotStageHistory(const std::vector<StagePoint>& points) {
  const int W = 900, H = 420, L = 70, R = 30, T = 30, B = 50;
  cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
  if (points.size() < 2) return img;
  double t_max = 0, lo = 1e9, hi = -1e9;
  for (const StagePoint& p : points) {
    t_max = std::max(t_max, p.seconds / 3600);
    lo = std::min(lo, p.psnr), hi = std::max(hi, p.psnr);
  }
  lo = std::floor(lo - 0.5), hi = std::ceil(hi + 0.5);
  auto px = [&](double h) { return L + static_cast<int>((W - L - R) * h / std::max(t_max, 1e-6)); };
  auto py = [&](double v) { return T + static_cast<int>((H - T - B) * (1 - (v - lo) / (hi - lo))); };
  cv::rectangle(img, {L, T}, {W - R, H - B}, cv::Scalar(0, 0, 0));
  const cv::Scalar blue(30, 60, 200), black(0, 0, 0);
  for (size_t i = 0; i < points.size(); ++i) {
    const cv::Point p(px(points[i].seconds / 3600), py(points[i].psnr));
    cv::circle(img, p, 3, blue, cv::FILLED);
    if (i > 0) cv::line(img, {px(points[i - 1].seconds / 3600), py(points[i - 1].psnr)}, p, blue, 1);
  }
  auto text = [&](const std::string& s, int x, int y) {
    cv::putText(img, s, {x, y}, cv::FONT_HERSHEY_SIMPLEX, 0.45, black, 1);
  };
  text(absl::StrFormat("%.0f dB", hi), 5, T + 10);
  text(absl::StrFormat("%.0f dB", lo), 5, H - B);
  text(absl::StrFormat("held-out PSNR at each stage end against training time, 0 .. %.2f h (last: %.2f dB at "
                       "iteration %d)",
                       t_max, points.back().psnr, points.back().iteration),
       L, H - 15);
  return img;  // drawn in RGB order
}

}  // namespace streetsim::train
