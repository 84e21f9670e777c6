#include "scene/eval/decomposition.h"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <filesystem>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/str_cat.h"
#include "render/common/log.h"
#include "scene/train/dynamic_stage.h"
#include "scene/train/image_file.h"

namespace streetsim::train {

absl::StatusOr<StaticDynamicSplit> SplitStaticDynamic(const field::DeformationField* field,
                                                      const GaussianStore& canonical, ThreadPool& pool,
                                                      const field::StaticSkipOptions& options) {
  StaticDynamicSplit split;
  split.has_field = field != nullptr;
  std::vector<uint8_t> dynamic(canonical.size(), 0);
  if (field) {
    absl::StatusOr<field::StaticAnalysis> a = field::AnalyseStatic(*field, canonical, options, pool);
    if (!a.ok()) return a.status();
    for (uint32_t r : a->dynamic_rows) dynamic[r] = 1;
    split.dynamic_rows = std::move(a->dynamic_rows);
  }
  split.static_rows.reserve(canonical.size() - split.dynamic_rows.size());
  for (size_t i = 0; i < canonical.size(); ++i) {
    if (!dynamic[i]) split.static_rows.push_back(static_cast<uint32_t>(i));
  }
  return split;
}

GaussianStore SelectRows(const GaussianStore& g, const std::vector<uint32_t>& rows) {
  GaussianStore out;
  out.sh_degree = g.sh_degree;
  const size_t K3 = static_cast<size_t>(g.sh_coeffs()) * 3;
  const bool normals = g.normals.size() == g.size() * 3;
  if (normals) out.normals.resize(rows.size() * 3);
  out.Resize(rows.size());
  for (size_t j = 0; j < rows.size(); ++j) {
    const size_t i = rows[j];
    std::copy_n(g.means.begin() + i * 3, 3, out.means.begin() + j * 3);
    std::copy_n(g.log_scales.begin() + i * 3, 3, out.log_scales.begin() + j * 3);
    std::copy_n(g.rotations.begin() + i * 4, 4, out.rotations.begin() + j * 4);
    out.opacity_logits[j] = g.opacity_logits[i];
    std::copy_n(g.sh.begin() + i * K3, K3, out.sh.begin() + j * K3);
    if (normals) std::copy_n(g.normals.begin() + i * 3, 3, out.normals.begin() + j * 3);
  }
  return out;
}

Decomposer::Decomposer(Engine& engine, const GaussianStore& canonical,
                       std::shared_ptr<const field::DeformationField> field, const Eigen::Vector3f& background)
    : engine_(engine), canonical_(canonical), field_(std::move(field)), background_(background) {}

absl::StatusOr<std::unique_ptr<Decomposer>> Decomposer::Create(Engine& engine, const GaussianStore& canonical,
                                                               std::shared_ptr<const field::DeformationField> field,
                                                               const Eigen::Vector3f& background) {
  if (absl::Status s = canonical.Validate(); !s.ok()) return s;
  if (field && canonical.sh_degree != 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("a scene with a field needs SH degree 3 Gaussians, this one has degree ", canonical.sh_degree));
  }
  std::unique_ptr<Decomposer> d(new Decomposer(engine, canonical, std::move(field), background));
  const auto start = std::chrono::steady_clock::now();
  absl::StatusOr<StaticDynamicSplit> split = SplitStaticDynamic(d->field_.get(), canonical, d->pool_);
  if (!split.ok()) return split.status();
  d->split_ = std::move(*split);
  if (d->field_) {
    LOG(INFO) << "decomposition: " << d->split_.static_rows.size() << " static, " << d->split_.dynamic_rows.size()
              << " dynamic Gaussians (analysis "
              << std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() << " s)";
  }
  return d;
}

absl::Status Decomposer::UploadAt(int64_t time_us) {
  // A static scene once; a field scene once per time (several cameras of a frame share it).
  if (uploaded_ && (!field_ || time_us == uploaded_time_us_)) return absl::OkStatus();
  GaussianStore at_time;
  if (field_) {
    absl::StatusOr<GaussianStore> d = DeformedStore(*field_, canonical_, time_us, pool_);
    if (!d.ok()) return d.status();
    at_time = std::move(*d);
  }
  const GaussianStore& scene = field_ ? at_time : canonical_;
  if (absl::Status s = engine_.UpdateScene(scene, &full_); !s.ok()) return s;
  if (absl::Status s = engine_.UpdateScene(SelectRows(scene, split_.static_rows), &static_); !s.ok()) return s;
  if (absl::Status s = engine_.UpdateScene(SelectRows(scene, split_.dynamic_rows), &dynamic_); !s.ok()) return s;
  uploaded_ = true;
  uploaded_time_us_ = time_us;
  return absl::OkStatus();
}

absl::StatusOr<DecompositionRenders> Decomposer::Render(const PinholeCamera& camera, int64_t time_us) {
  if (absl::Status s = UploadAt(time_us); !s.ok()) return s;
  RenderOptions ro;
  ro.background = background_;
  RenderOptions black = ro;
  black.background = Eigen::Vector3f::Zero();
  DecompositionRenders r;
  RenderOutput out;
  if (absl::Status s = engine_.Render(*full_, camera, ro, &out); !s.ok()) return s;
  r.width = out.width;
  r.height = out.height;
  r.full = std::move(out.rgb);
  if (absl::Status s = engine_.Render(*static_, camera, ro, &out); !s.ok()) return s;
  r.static_only = std::move(out.rgb);
  if (absl::Status s = engine_.Render(*dynamic_, camera, black, &out); !s.ok()) return s;
  r.dynamic_only = std::move(out.rgb);
  r.dynamic_alpha = std::move(out.alpha);
  return r;
}

cv::Mat RgbToMat8(const std::vector<float>& rgb, int width, int height) {
  cv::Mat m(height, width, CV_8UC3);
  for (int y = 0; y < height; ++y) {
    uint8_t* row = m.ptr<uint8_t>(y);
    for (int x = 0; x < width * 3; ++x) {
      const float v = std::clamp(rgb[static_cast<size_t>(y) * width * 3 + x], 0.0f, 1.0f);
      row[x] = static_cast<uint8_t>(std::lround(v * 255.0f));
    }
  }
  return m;
}

cv::Mat DynamicMaskOverlay(const View& view) {
  const int W = view.camera.width, H = view.camera.height;
  if (view.dynamic_pixels.size() != static_cast<size_t>(W) * H || view.rgb8.cols != W || view.rgb8.rows != H) {
    return cv::Mat();
  }
  cv::Mat out = view.rgb8.clone();
  for (int y = 0; y < H; ++y) {
    uint8_t* row = out.ptr<uint8_t>(y);
    for (int x = 0; x < W; ++x) {
      if (!view.dynamic_pixels[static_cast<size_t>(y) * W + x]) continue;
      row[x * 3] = static_cast<uint8_t>((row[x * 3] + 255 + 1) / 2);
      row[x * 3 + 1] = static_cast<uint8_t>(row[x * 3 + 1] / 2);
      row[x * 3 + 2] = static_cast<uint8_t>(row[x * 3 + 2] / 2);
    }
  }
  return out;
}

std::string DecompositionStem(const View& view) {
  std::string name = view.name;
  const std::string ext = std::filesystem::path(name).extension().string();
  if (!ext.empty() && ext.size() <= 5) name.resize(name.size() - ext.size());
  for (char& c : name) {
    if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' || c == '.')) c = '_';
  }
  if (name.empty() || name[0] == '.') name = absl::StrCat("frame", view.frame, name);
  return name;
}

absl::Status WriteRgbMatAtomic(const std::string& path, const cv::Mat& rgb8) {
  cv::Mat bgr;
  cv::cvtColor(rgb8, bgr, cv::COLOR_RGB2BGR);
  return WriteImageAtomic(path, bgr);
}

absl::Status WriteDecompositionPngs(const std::string& dir, const View& view, const DecompositionRenders& r) {
  const std::string stem = (std::filesystem::path(dir) / DecompositionStem(view)).string();
  const std::pair<const char*, const std::vector<float>*> images[] = {
      {"_full.png", &r.full}, {"_static.png", &r.static_only}, {"_dynamic.png", &r.dynamic_only}};
  for (const auto& [suffix, rgb] : images) {
    if (absl::Status s = WriteRgbMatAtomic(stem + suffix, RgbToMat8(*rgb, r.width, r.height)); !s.ok()) return s;
  }
  const cv::Mat mask = DynamicMaskOverlay(view);
  if (!mask.empty()) {
    if (absl::Status s = WriteRgbMatAtomic(stem + "_mask.png", mask); !s.ok()) return s;
  }
  return absl::OkStatus();
}

}  // namespace streetsim::train
