#include "server/trained_outputs.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <optional>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/train/clips.h"
#include "scene/eval/metrics_json.h"

namespace streetsim::server {
namespace fs = std::filesystem;

namespace {
constexpr int64_t kMaxPreviewFileBytes = 64 << 20;
constexpr int kPreviewMaxWidth = 384;

// A clip set's clip directories, from its manifest (clips.h), in clip order; nullopt for a plain
// scene. A manifest the trainer's own reader refuses is an error.
absl::StatusOr<std::optional<std::vector<std::string>>> ClipDirs(const std::string& work) {
  absl::StatusOr<std::optional<train::ClipSet>> set = train::ReadClipSet(work);
  if (!set.ok()) return set.status();
  if (!*set) return std::nullopt;
  std::vector<std::string> dirs;
  for (const train::ClipEntry& c : (*set)->clips) dirs.push_back((fs::path(work) / c.dir).string());
  return dirs;
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
  absl::StatusOr<std::optional<std::vector<std::string>>> clips = ClipDirs(work);
  if (!clips.ok()) {
    LOG(WARNING) << "trained Gaussians: " << clips.status().message();
    return 0;
  }
  if (!*clips) return PlyVertexCount(work + "/scene.ply");
  uint64_t n = 0;
  for (const std::string& d : **clips) n += PlyVertexCount(d + "/scene.ply");
  return n;
}

v1::HeldOutMetrics TrainedHeldoutMetrics(const std::string& work) {
  absl::StatusOr<std::optional<std::vector<std::string>>> clips = ClipDirs(work);
  if (!clips.ok()) {
    LOG(WARNING) << "held-out metrics: " << clips.status().message();
    return {};
  }
  std::vector<train::EvalResult> parts;
  for (const std::string& d : clips->value_or(std::vector<std::string>{work})) {
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

absl::StatusOr<train::SceneMeta> TrainedSceneMeta(const std::string& work) {
  absl::StatusOr<std::optional<std::vector<std::string>>> clips = ClipDirs(work);
  if (!clips.ok()) return clips.status();
  if (*clips && (*clips)->empty()) return absl::DataLossError(absl::StrCat(work, ": a clip set without clips"));
  return train::ReadSceneMeta(*clips ? (*clips)->front() : work);
}

bool HasTrainerCheckpoint(const std::string& work) {
  return fs::exists(work + "/checkpoint.bin") || fs::exists(fs::path(work) / train::kClipManifestName);
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
