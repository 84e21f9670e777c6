#include "server/trained_outputs.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <optional>
#include <vector>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/numbers.h"
#include "render/common/log.h"
#include "scene/train/clips.h"
#include "scene/train/metrics_json.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {
constexpr int64_t kMaxPreviewFileBytes = 64 << 20;
constexpr int kPreviewMaxWidth = 384;

// A clip set's clip directories (WORK/clips.json beside WORK/clip_KKK/), sorted; nullopt for a
// plain scene.
std::optional<std::vector<std::string>> ClipDirs(const std::string& work) {
  if (!fs::exists(work + "/clips.json")) return std::nullopt;
  std::vector<std::string> dirs;
  std::error_code ec;
  for (fs::directory_iterator it(work, ec), end; !ec && it != end; it.increment(ec)) {
    if (it->path().filename().string().rfind("clip_", 0) == 0) dirs.push_back(it->path().string());
  }
  std::sort(dirs.begin(), dirs.end());
  return dirs;
}
// WORK/train_meta.json (a clip set: its first clip's) as an object; empty when unreadable.
nlohmann::json TrainMeta(const std::string& work) {
  const std::optional<std::vector<std::string>> clips = ClipDirs(work);
  const std::string dir = !clips ? work : clips->empty() ? "" : clips->front();
  std::ifstream in(dir + "/train_meta.json");
  if (dir.empty() || !in) return nlohmann::json::object();
  nlohmann::json meta = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  return meta.is_object() ? meta : nlohmann::json::object();
}

}  // namespace

uint64_t PlyVertexCount(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::string line;
  for (int i = 0; i < 64 && std::getline(in, line); ++i) {
    if (line.rfind("element vertex ", 0) == 0) {
      uint64_t n = 0;
      if (absl::SimpleAtoi(line.substr(15), &n)) return n;
    }
    if (line.rfind("end_header", 0) == 0) break;
  }
  return 0;
}

uint64_t TrainedGaussianCount(const std::string& work) {
  const std::optional<std::vector<std::string>> clips = ClipDirs(work);
  if (!clips) return PlyVertexCount(work + "/scene.ply");
  uint64_t n = 0;
  for (const std::string& d : *clips) n += PlyVertexCount(d + "/scene.ply");
  return n;
}

v1::HeldOutMetrics TrainedHeldoutMetrics(const std::string& work) {
  const std::vector<std::string> dirs = ClipDirs(work).value_or(std::vector<std::string>{work});
  std::vector<train::EvalResult> parts;
  for (const std::string& d : dirs) {
    absl::StatusOr<train::EvalResult> r = train::ReadHeldoutMetrics(d);
    if (absl::IsNotFound(r.status())) continue;
    if (!r.ok()) {
      LOG(WARNING) << "held-out metrics: " << r.status().message();
      return {};
    }
    parts.push_back(std::move(*r));
  }
  v1::HeldOutMetrics out;
  if (parts.empty()) return out;
  const train::EvalResult all = parts.size() == 1 ? parts[0] : train::MergeEvalResults(parts);
  out.set_views(static_cast<int32_t>(all.frames.size()));
  out.set_psnr_db(all.mean.psnr);
  out.set_ssim(all.mean.ssim);
  out.set_psnr_dynamic_db(all.mean.psnr_dynamic);
  return out;
}

int64_t TrainedIterations(const std::string& work) {
  const nlohmann::json meta = TrainMeta(work);
  return meta.contains("iterations") && meta["iterations"].is_number_integer() ? meta["iterations"].get<int64_t>() : 0;
}

std::string TrainedField(const std::string& work) {
  const nlohmann::json meta = TrainMeta(work);
  return meta.contains("field") && meta["field"].is_string() ? meta["field"].get<std::string>() : "";
}

bool HasTrainerCheckpoint(const std::string& work) {
  return fs::exists(work + "/checkpoint.bin") || fs::exists(work + "/clips.json");
}

std::string FirstPreviewPng(const std::string& work) {
  std::error_code ec;
  std::vector<std::string> pngs;
  for (fs::directory_iterator it(work + "/preview", ec), end; !ec && it != end; it.increment(ec)) {
    if (it->path().extension() == ".png") pngs.push_back(it->path().string());
  }
  if (pngs.empty()) return "";
  std::sort(pngs.begin(), pngs.end());
  if (fs::file_size(pngs.front(), ec) > static_cast<uintmax_t>(kMaxPreviewFileBytes) || ec) return "";
  cv::Mat image = cv::imread(pngs.front(), cv::IMREAD_COLOR);
  if (image.empty()) return "";
  if (image.cols > kPreviewMaxWidth) {
    const int height = std::max(1, image.rows * kPreviewMaxWidth / image.cols);
    cv::Mat small;
    cv::resize(image, small, cv::Size(kPreviewMaxWidth, height), 0, 0, cv::INTER_AREA);
    image = small;
  }
  std::vector<uchar> png;
  if (!cv::imencode(".png", image, png)) return "";
  return std::string(png.begin(), png.end());
}

}  // namespace streetsim::server
