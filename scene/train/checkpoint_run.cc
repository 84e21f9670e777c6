#include "scene/train/checkpoint_run.h"

#include <filesystem>
#include <fstream>
#include <functional>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"

namespace streetsim::train {

absl::Status WriteCheckpointRun(const std::string& dir, const CheckpointRun& run) {
  nlohmann::json j;
  j["iteration"] = run.iteration;
  j["field"] = run.field;
  if (run.field_extension_from > 0) j["field_extension_from"] = run.field_extension_from;
  if (run.guard && run.guard->started) {
    j["guard"] = {{"baseline", run.guard->baseline}, {"mean", run.guard->mean}, {"best", run.guard->best},
                  {"psnr_mean", run.guard->psnr_mean}, {"psnr_best", run.guard->psnr_best},
                  {"image_width", run.guard->image_width}};
  }
  return checked_file::WriteAtomically((std::filesystem::path(dir) / kCheckpointRunFile).string(), j.dump(2) + "\n");
}

namespace {

// `parse` applied to the JSON in `path`: NotFound without the file, DataLoss naming it where it is
// not JSON or a value has the wrong type (nlohmann throws; nothing is thrown past here).
template <typename T>
absl::StatusOr<T> ParseJsonFile(const std::string& path,
                                const std::function<absl::StatusOr<T>(const nlohmann::json&)>& parse) {
  std::ifstream f(path);
  if (!f) return absl::NotFoundError(absl::StrCat("no ", path));
  try {
    return parse(nlohmann::json::parse(f));
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

std::string RunFile(const std::string& dir) { return (std::filesystem::path(dir) / kCheckpointRunFile).string(); }

}  // namespace

absl::StatusOr<std::string> ReadCheckpointField(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::string>(path, [&](const nlohmann::json& j) -> absl::StatusOr<std::string> {
    const std::string field = j.at("field").get<std::string>();
    if (field != "static" && field != "s3gaussian" && field != "extended") {
      return absl::DataLossError(absl::StrCat(path, ": unknown field '", field, "'"));
    }
    return field;
  });
}

absl::StatusOr<int64_t> ReadCheckpointExtensionFrom(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<int64_t>(path, [&](const nlohmann::json& j) -> absl::StatusOr<int64_t> {
    if (!j.contains("field_extension_from")) return 0;
    const int64_t from = j.at("field_extension_from").get<int64_t>();
    if (from < 0) return absl::DataLossError(absl::StrCat(path, ": field_extension_from is negative"));
    return from;
  });
}

std::optional<DivergenceGuardState> ReadCheckpointGuard(const std::string& dir, int64_t iteration) {
  absl::StatusOr<std::optional<DivergenceGuardState>> g = ParseJsonFile<std::optional<DivergenceGuardState>>(
      RunFile(dir), [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<DivergenceGuardState>> {
        if (!j.contains("guard") || j.value("iteration", int64_t{-1}) != iteration) return std::nullopt;
        const nlohmann::json& r = j.at("guard");
        DivergenceGuardState s;
        s.started = true;
        s.baseline = r.at("baseline").get<int64_t>();
        s.mean = r.at("mean").get<double>();
        s.best = r.at("best").get<double>();
        s.psnr_mean = r.at("psnr_mean").get<double>();
        s.psnr_best = r.at("psnr_best").get<double>();
        s.image_width = r.at("image_width").get<int>();
        return std::optional<DivergenceGuardState>(s);
      });
  return g.ok() ? *g : std::nullopt;
}

}  // namespace streetsim::train
