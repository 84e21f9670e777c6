#include "scene/eval/eval_outputs.h"

#include <filesystem>

#include "absl/strings/str_cat.h"

namespace streetsim::train {

absl::Status PrepareEvalOutputs(const EvalOutputOptions& o) {
  if (!o.decomposition_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(o.decomposition_dir, ec);
    if (ec || !std::filesystem::is_directory(o.decomposition_dir, ec)) {
      return absl::InvalidArgumentError(
          absl::StrCat("--decomposition ", o.decomposition_dir, ": cannot create the directory",
                       ec ? absl::StrCat(": ", ec.message()) : std::string()));
    }
  }
  if (!o.video_path.empty()) return CheckVideoPath(o.video_path);
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<EvalOutputs>> EvalOutputs::Create(Engine& engine, const EvalOutputOptions& options) {
  if (absl::Status s = PrepareEvalOutputs(options); !s.ok()) return s;
  std::unique_ptr<EvalOutputs> out(new EvalOutputs(engine, options));
  if (!options.video_path.empty()) out->video_ = std::make_unique<EvalVideo>(options.video_path, options.video_fps);
  return out;
}

absl::Status EvalOutputs::UseScene(const GaussianStore& canonical, std::shared_ptr<const field::DeformationField> field,
                                   const Eigen::Vector3f& background) {
  decomposer_.reset();
  // The video's third panel (dynamic Gaussians only) needs the split too, when there is a field.
  if (options_.decomposition_dir.empty() && !(video_ && field)) return absl::OkStatus();
  absl::StatusOr<std::unique_ptr<Decomposer>> d = Decomposer::Create(engine_, canonical, std::move(field), background);
  if (!d.ok()) return d.status();
  decomposer_ = std::move(*d);
  EvalOutputSummary::Split& split = summary_.split ? *summary_.split : summary_.split.emplace();
  ++split.scenes;
  split.scenes_with_field += decomposer_->split().has_field;
  split.static_gaussians += decomposer_->split().static_rows.size();
  split.dynamic_gaussians += decomposer_->split().dynamic_rows.size();
  return absl::OkStatus();
}

EvalFrameSink EvalOutputs::sink() {
  return [this](const View& view, const std::vector<float>& rgb) { return AddView(view, rgb); };
}

absl::Status EvalOutputs::AddView(const View& view, const std::vector<float>& rgb) {
  const int W = view.camera.width, H = view.camera.height;
  if (rgb.size() != static_cast<size_t>(W) * H * 3) return absl::InternalError("eval outputs: render size mismatch");
  if (!options_.decomposition_dir.empty() && !decomposer_) {
    return absl::FailedPreconditionError("eval outputs: a view before UseScene");
  }
  std::optional<DecompositionRenders> parts;
  if (decomposer_) {
    absl::StatusOr<DecompositionRenders> r = decomposer_->Render(view.camera, view.time_us);
    if (!r.ok()) return r.status();
    parts = std::move(*r);
  }
  if (!options_.decomposition_dir.empty()) {
    if (absl::Status s = WriteDecompositionPngs(options_.decomposition_dir, view, *parts); !s.ok()) return s;
    ++summary_.decomposition_views;
  }
  if (video_) {
    const cv::Mat gt = view.rgb8.empty() ? cv::Mat(H, W, CV_8UC3, cv::Scalar(0, 0, 0)) : view.rgb8;
    std::vector<cv::Mat> panels = {RgbToMat8(rgb, W, H), gt};
    std::vector<std::string> labels = {"rendered", "ground truth"};
    if (parts && decomposer_->split().has_field) {
      panels.push_back(RgbToMat8(parts->dynamic_only, parts->width, parts->height));
      labels.push_back("dynamic Gaussians");
    }
    const std::string camera = view.name.substr(0, view.name.find('/'));
    if (absl::Status s = video_->Add(view.time_us, camera, panels, labels); !s.ok()) return s;
  }
  return absl::OkStatus();
}

absl::StatusOr<EvalOutputSummary> EvalOutputs::Finish() {
  if (video_) {
    absl::StatusOr<VideoSummary> v = video_->Write();
    if (!v.ok()) return v.status();
    summary_.video = std::move(*v);
  }
  return summary_;
}

}  // namespace streetsim::train
