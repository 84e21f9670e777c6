#include "scene/eval/metrics_json.h"

#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"

#include "scene/common/checked_file.h"

namespace streetsim::train {
nlohmann::json MetricOrNull(double v) { return v >= 0 ? nlohmann::json(v) : nlohmann::json(nullptr); }

nlohmann::json FrameMetricsJson(const FrameMetrics& m) {
  nlohmann::json j;
  j["psnr"] = m.psnr;
  j["ssim"] = m.ssim;
  j["depth_median_abs_m"] = MetricOrNull(m.depth_median_abs_m);
  j["depth_within_5pct"] = MetricOrNull(m.depth_within_5pct);
  // PSNR* (dynamic_pixels.h); null: no dynamic (static) pixel in the view(s).
  j["psnr_dynamic"] = MetricOrNull(m.psnr_dynamic);
  j["psnr_static"] = MetricOrNull(m.psnr_static);
  return j;
}

nlohmann::json EvalResultJson(const EvalResult& r) {
  nlohmann::json j;
  j["views"] = r.frames.size();
  j["frames"] = nlohmann::json::array();
  for (const FrameMetrics& f : r.frames) {
    nlohmann::json fj = FrameMetricsJson(f);
    fj["name"] = f.name;
    fj["frame"] = f.frame;
    j["frames"].push_back(fj);
  }
  j["mean"] = FrameMetricsJson(r.mean);
  return j;
}

absl::Status WriteHeldoutMetrics(const std::string& dir, const EvalResult& heldout) {
  return checked_file::WriteAtomically((std::filesystem::path(dir) / kHeldoutMetricsFileName).string(),
                                       EvalResultJson(heldout).dump(2) + "\n");
}

absl::StatusOr<EvalResult> ReadHeldoutMetrics(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kHeldoutMetricsFileName).string();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return absl::NotFoundError(absl::StrCat(path, ": no such file"));
  std::ifstream in(path);
  const nlohmann::json j = nlohmann::json::parse(in, nullptr, /*allow_exceptions=*/false);
  auto bad = [&](const std::string& why) { return absl::DataLossError(absl::StrCat(path, ": ", why)); };
  if (j.is_discarded() || !j.is_object()) return bad("not JSON");
  auto metrics = [](const nlohmann::json& o, FrameMetrics* m) {
    if (!o.is_object() || !o.contains("psnr") || !o.contains("ssim") || !o["psnr"].is_number() ||
        !o["ssim"].is_number()) {
      return false;
    }
    auto number_or = [&](const char* key) { return o.contains(key) && o[key].is_number() ? o[key].get<double>() : -1.0; };
    m->psnr = o["psnr"].get<double>();
    m->ssim = o["ssim"].get<double>();
    m->depth_median_abs_m = number_or("depth_median_abs_m");
    m->depth_within_5pct = number_or("depth_within_5pct");
    m->psnr_dynamic = number_or("psnr_dynamic");
    m->psnr_static = number_or("psnr_static");
    return true;
  };
  EvalResult r;
  if (!j.contains("frames") || !j["frames"].is_array()) return bad("no \"frames\" array");
  for (const nlohmann::json& f : j["frames"]) {
    FrameMetrics m;
    if (!metrics(f, &m) || !f.contains("frame") || !f["frame"].is_number_integer()) return bad("a frame without its metrics");
    m.frame = f["frame"].get<int>();
    if (f.contains("name") && f["name"].is_string()) m.name = f["name"].get<std::string>();
    r.frames.push_back(m);
  }
  if (!j.contains("mean") || !metrics(j["mean"], &r.mean)) return bad("no \"mean\" metrics");
  return r;
}

}  // namespace streetsim::train
