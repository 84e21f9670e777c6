#include "scene/train/checkpoint_run.h"

#include <filesystem>
#include <fstream>
#include <functional>

#include <nlohmann/json.hpp>

#include "absl/strings/str_cat.h"
#include "scene/common/checked_file.h"
#include "scene/train/motion_prior.h"
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
  if (run.pose_refinement) {
    j["pose_rotation_lr"] = run.pose_refinement->rotation_lr;
    j["pose_translation_lr"] = run.pose_refinement->translation_lr;
    j["pose_refine_from"] = run.pose_refinement->from;
    j["pose_refine_until"] = run.pose_refinement->until;
  }
  j["position_lr_decay_iterations"] = run.position_lr_decay_iterations;
  j["densify_until"] = run.densify_until;
  if (run.field_extension_from > 0) j["field_extension_from"] = run.field_extension_from;
  if (run.field_ext_lr) {
    j["field_ext_lr_scale"] = run.field_ext_lr->scale;
    j["field_ext_lr_decay_iterations"] = run.field_ext_lr->decay_iterations;
  }
  if (run.field_motion_prior) j["field_motion_prior"] = *run.field_motion_prior;
  if (run.field_motion_prior_all_scans) {
    j["field_motion_prior_scans"] = MotionPriorScansName(*run.field_motion_prior_all_scans);
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

// The schedule `j` records under `prefix` + "_scale" / "_decay_iterations" (nullopt: neither
// key); throws where a key is missing or mistyped.
absl::StatusOr<std::optional<FieldLrSchedule>> LrScheduleIn(const nlohmann::json& j, const std::string& path,
                                                            const std::string& prefix = "field_lr") {
  const std::string scale_key = prefix + "_scale", decay_key = prefix + "_decay_iterations";
  if (!j.contains(scale_key) && !j.contains(decay_key)) return std::nullopt;
  FieldLrSchedule lr;
  lr.scale = j.at(scale_key).get<double>();
  lr.decay_iterations = j.at(decay_key).get<int>();
  if (!(lr.scale > 0 && lr.scale <= 1000) || lr.decay_iterations < 1) {
    return absl::DataLossError(absl::StrCat(path, ": ", prefix, " schedule out of range"));
  }
  return std::optional<FieldLrSchedule>(lr);
}

// The integer the file records under `key` (nullopt without it); DataLoss saying "`what` out of
// range" outside [lo, hi].
absl::StatusOr<std::optional<int>> ReadRecordedInt(const std::string& dir, const std::string& key, int lo, int hi,
                                                   const std::string& what) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<int>>(path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<int>> {
    if (!j.contains(key)) return std::nullopt;
    const int n = j.at(key).get<int>();
    if (n < lo || n > hi) return absl::DataLossError(absl::StrCat(path, ": ", what, " out of range"));
    return std::optional<int>(n);
  });
}

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

absl::StatusOr<std::optional<FieldLrSchedule>> ReadCheckpointFieldLr(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<FieldLrSchedule>>(path, [&](const nlohmann::json& j) { return LrScheduleIn(j, path); });
}

absl::StatusOr<std::optional<FieldLrSchedule>> ReadCheckpointExtLr(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<FieldLrSchedule>>(
      path, [&](const nlohmann::json& j) { return LrScheduleIn(j, path, "field_ext_lr"); });
}

absl::StatusOr<std::optional<LowResStage>> ReadCheckpointLowResStage(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<LowResStage>>(
      path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<LowResStage>> {
        if (!j.contains("low_res_scale") && !j.contains("low_res_iterations")) return std::nullopt;
        LowResStage low;
        low.resolution_scale = j.at("low_res_scale").get<double>();
        low.iterations = j.at("low_res_iterations").get<int64_t>();
        if (!(low.resolution_scale > 0 && low.resolution_scale <= 1) || low.iterations < 1) {
          return absl::DataLossError(absl::StrCat(path, ": low-resolution stage out of range"));
        }
        return std::optional<LowResStage>(low);
      });
}

absl::StatusOr<std::optional<PoseRefinementSchedule>> ReadCheckpointPoseRefinement(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<PoseRefinementSchedule>>(
      path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<PoseRefinementSchedule>> {
        if (!j.contains("pose_rotation_lr")) return std::nullopt;
        PoseRefinementSchedule pose;
        pose.rotation_lr = j.at("pose_rotation_lr").get<double>();
        pose.translation_lr = j.at("pose_translation_lr").get<double>();
        pose.from = j.at("pose_refine_from").get<int>();
        pose.until = j.at("pose_refine_until").get<int64_t>();
        if (!(pose.rotation_lr >= 0 && pose.rotation_lr <= 1) ||
            !(pose.translation_lr >= 0 && pose.translation_lr <= 10) || pose.from < 0 || pose.until < 0) {
          return absl::DataLossError(absl::StrCat(path, ": pose refinement schedule out of range"));
        }
        return std::optional<PoseRefinementSchedule>(pose);
      });
}

absl::StatusOr<std::optional<int>> ReadCheckpointPositionLrDecay(const std::string& dir) {
  return ReadRecordedInt(dir, "position_lr_decay_iterations", 1, 10'000'000, "position learning-rate decay");
}

absl::StatusOr<std::optional<int>> ReadCheckpointDensifyUntil(const std::string& dir) {
  return ReadRecordedInt(dir, "densify_until", 0, kMaxDensifyUntil, "densify_until");
}

absl::StatusOr<std::optional<double>> ReadCheckpointMotionPrior(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<double>>(
      path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<double>> {
        if (!j.contains("field_motion_prior")) return std::nullopt;
        const double w = j.at("field_motion_prior").get<double>();
        if (!(w >= 0 && w <= kMaxMotionPriorWeight)) {
          return absl::DataLossError(absl::StrCat(path, ": field_motion_prior out of range"));
        }
        return std::optional<double>(w);
      });
}

absl::StatusOr<std::optional<bool>> ReadCheckpointMotionPriorAllScans(const std::string& dir) {
  const std::string path = RunFile(dir);
  return ParseJsonFile<std::optional<bool>>(path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<bool>> {
    if (!j.contains("field_motion_prior_scans")) return std::nullopt;
    const std::optional<bool> all_scans = ParseMotionPriorScans(j.at("field_motion_prior_scans").get<std::string>());
    if (!all_scans) {
      return absl::DataLossError(absl::StrCat(path, ": field_motion_prior_scans is neither \"all\" nor \"last\""));
    }
    return all_scans;
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

absl::StatusOr<std::optional<FieldLrSchedule>> ReadTrainMetaFieldLr(const std::string& dir) {
  const std::filesystem::path d(dir);
  absl::StatusOr<int64_t> at = PeekCheckpointIteration((d / "checkpoint.bin").string());
  if (!at.ok()) return std::nullopt;
  const std::string path = (d / "train_meta.json").string();
  absl::StatusOr<std::optional<FieldLrSchedule>> lr = ParseJsonFile<std::optional<FieldLrSchedule>>(
      path, [&](const nlohmann::json& j) -> absl::StatusOr<std::optional<FieldLrSchedule>> {
        // Another iteration's file describes another segment, whose schedule may differ.
        if (!j.contains("iterations") || j.at("iterations").get<int64_t>() != *at) return std::nullopt;
        return LrScheduleIn(j, path);
      });
  if (absl::IsNotFound(lr.status())) return std::nullopt;
  return lr;
}

}  // namespace streetsim::train
