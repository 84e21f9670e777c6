#include "scene/train/checkpoint_run.h"

#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"
#include "scene/train/train_state.h"

namespace streetsim::train {

absl::Status WriteCheckpointRun(const std::string& dir, const CheckpointRun& run) {
  nlohmann::json j;
  j["iteration"] = run.iteration;
  j["field"] = run.field;
  if (run.static_iterations) j["static_iterations"] = *run.static_iterations;
  if (run.field_lr) {
    j["field_lr_scale"] = run.field_lr->scale;
    j["field_lr_decay_iterations"] = run.field_lr->decay_iterations;
  }
  if (run.low_res) {
    j["low_res_scale"] = run.low_res->resolution_scale;
    j["low_res_iterations"] = run.low_res->iterations;
  }
  return checked_file::WriteAtomically((std::filesystem::path(dir) / kCheckpointRunFile).string(), j.dump(2) + "\n");
}

absl::StatusOr<std::string> ReadCheckpointField(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kCheckpointRunFile).string();
  std::ifstream f(path);
  if (!f) return absl::NotFoundError(absl::StrCat("no ", path));
  try {
    const std::string field = nlohmann::json::parse(f).at("field").get<std::string>();
    if (field != "static" && field != "s3gaussian" && field != "extended") {
      return absl::DataLossError(absl::StrCat(path, ": unknown field '", field, "'"));
    }
    return field;
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

absl::StatusOr<std::optional<FieldLrSchedule>> ReadCheckpointFieldLr(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kCheckpointRunFile).string();
  std::ifstream f(path);
  if (!f) return absl::NotFoundError(absl::StrCat("no ", path));
  try {
    const nlohmann::json j = nlohmann::json::parse(f);
    if (!j.contains("field_lr_scale") && !j.contains("field_lr_decay_iterations")) {
      return std::optional<FieldLrSchedule>();
    }
    FieldLrSchedule lr;
    lr.scale = j.at("field_lr_scale").get<double>();
    lr.decay_iterations = j.at("field_lr_decay_iterations").get<int>();
    if (!(lr.scale > 0 && lr.scale <= 1000) || lr.decay_iterations < 1) {
      return absl::DataLossError(absl::StrCat(path, ": field learning-rate schedule out of range"));
    }
    return std::optional<FieldLrSchedule>(lr);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

absl::StatusOr<std::optional<LowResStage>> ReadCheckpointLowResStage(const std::string& dir) {
  const std::string path = (std::filesystem::path(dir) / kCheckpointRunFile).string();
  std::ifstream f(path);
  if (!f) return absl::NotFoundError(absl::StrCat("no ", path));
  try {
    const nlohmann::json j = nlohmann::json::parse(f);
    if (!j.contains("low_res_scale") && !j.contains("low_res_iterations")) {
      return std::optional<LowResStage>();
    }
    LowResStage c;
    c.resolution_scale = j.at("low_res_scale").get<double>();
    c.iterations = j.at("low_res_iterations").get<int64_t>();
    if (!(c.resolution_scale > 0 && c.resolution_scale <= 1) || c.iterations < 1) {
      return absl::DataLossError(absl::StrCat(path, ": low-resolution stage out of range"));
    }
    return std::optional<LowResStage>(c);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

absl::StatusOr<std::optional<FieldLrSchedule>> ReadTrainMetaFieldLr(const std::string& dir) {
  const std::filesystem::path d(dir);
  const std::string path = (d / "train_meta.json").string();
  std::ifstream f(path);
  if (!f) return std::optional<FieldLrSchedule>();
  absl::StatusOr<int64_t> at = PeekCheckpointIteration((d / "checkpoint.bin").string());
  if (!at.ok()) return std::optional<FieldLrSchedule>();
  try {
    const nlohmann::json j = nlohmann::json::parse(f);
    if (!j.contains("iterations") || j.at("iterations").get<int64_t>() != *at || !j.contains("field_lr_scale") ||
        !j.contains("field_lr_decay_iterations")) {
      return std::optional<FieldLrSchedule>();
    }
    FieldLrSchedule lr;
    lr.scale = j.at("field_lr_scale").get<double>();
    lr.decay_iterations = j.at("field_lr_decay_iterations").get<int>();
    if (!(lr.scale > 0 && lr.scale <= 1000) || lr.decay_iterations < 1) {
      return absl::DataLossError(absl::StrCat(path, ": field learning-rate schedule out of range"));
    }
    return std::optional<FieldLrSchedule>(lr);
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(path, ": ", e.what()));
  }
}

}  // namespace streetsim::train
