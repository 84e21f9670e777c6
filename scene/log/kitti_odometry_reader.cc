#include "scene/log/kitti_odometry_reader.h"

#include <cmath>
#include <filesystem>
#include <map>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "scene/log/poses_file.h"
#include "scene/log/text_util.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;

struct Projection {
  std::vector<double> p;  // 12, row-major
  int line = 0;
};

// calib.txt: "P0: ..." lines, or bare lines meaning P0, P1, ... in order.
absl::StatusOr<std::map<std::string, Projection>> ReadOdometryCalib(const std::string& path) {
  absl::StatusOr<std::vector<std::string>> lines = ReadLines(path);
  if (!lines.ok()) return lines.status();
  std::map<std::string, Projection> out;
  int bare = 0;
  for (size_t i = 0; i < lines->size(); ++i) {
    const std::string& line = (*lines)[i];
    if (IsBlankOrComment(line)) continue;
    std::string key, rest = line;
    if (const size_t colon = line.find(':'); colon != std::string::npos) {
      key = line.substr(0, colon);
      rest = line.substr(colon + 1);
    } else {
      key = absl::StrCat("P", bare++);
    }
    absl::StatusOr<std::vector<double>> v = ParseNumbers(rest, path, static_cast<int>(i + 1), 12);
    if (!v.ok()) return v.status();
    for (double x : *v) {
      if (!std::isfinite(x)) {
        return absl::InvalidArgumentError(absl::StrCat(path, ": line ", i + 1, ": non-finite value"));
      }
    }
    out[key] = {*std::move(v), static_cast<int>(i + 1)};
  }
  return out;
}

}  // namespace

Eigen::Isometry3d EgoFromOpenCvCamera() {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  // ego x (forward) = cam z, ego y (left) = -cam x, ego z (up) = -cam y.
  t.linear() << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  return t;
}

absl::StatusOr<DriveLog> ReadKittiOdometry(const std::string& sequence_dir) {
  const fs::path seq(sequence_dir);
  DriveLog log;
  log.format = "kitti_odometry";
  log.root = sequence_dir;
  const std::string calib_path = (seq / "calib.txt").string();
  absl::StatusOr<std::map<std::string, Projection>> calib = ReadOdometryCalib(calib_path);
  if (!calib.ok()) return calib.status();

  const std::vector<std::pair<std::string, std::string>> dirs = {
      {"image_0", "P0"}, {"image_1", "P1"}, {"image_2", "P2"}, {"image_3", "P3"},
      {"image_l", "P0"}, {"image_r", "P1"}};
  const Eigen::Isometry3d T_ego_from_cam0 = EgoFromOpenCvCamera();
  struct CamFiles {
    int slot;
    std::map<int, std::string> by_index;
  };
  std::vector<CamFiles> cam_files;
  for (const auto& [dir, key] : dirs) {
    if (!fs::is_directory(seq / dir)) continue;
    std::vector<int> indices;
    absl::StatusOr<std::vector<std::string>> files = ListNumberedFiles((seq / dir).string(), ".png", &indices);
    if (!files.ok()) return files.status();
    if (files->empty()) continue;
    auto it = calib->find(key);
    if (it == calib->end()) {
      return absl::InvalidArgumentError(absl::StrCat(calib_path, ": no ", key, " for ", dir));
    }
    const std::vector<double>& P = it->second.p;
    const std::string where = absl::StrCat(calib_path, ": line ", it->second.line, ": ", key);
    if (!(P[0] > 0) || !(P[5] > 0) || P[1] != 0 || P[4] != 0 || P[8] != 0 || P[9] != 0 || P[10] != 1) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": not a rectified projection K [I | t]"));
    }
    CameraSensor sensor;
    sensor.name = dir;
    sensor.colour = dir == "image_2" || dir == "image_3";
    CameraIntrinsics& k = sensor.intrinsics;
    k.fx = P[0];
    k.fy = P[5];
    k.cx = P[2];
    k.cy = P[6];
    cv::Mat probe;
    try {
      probe = cv::imread(files->front(), cv::IMREAD_UNCHANGED);
    } catch (const cv::Exception&) {
    }
    if (probe.empty()) return absl::DataLossError(absl::StrCat(files->front(), ": cannot decode image"));
    k.width = probe.cols;
    k.height = probe.rows;
    if (k.cx < 0 || k.cx > k.width || k.cy < 0 || k.cy > k.height) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": principal point (", k.cx, ", ", k.cy,
                                                     ") outside the ", k.width, "x", k.height, " image"));
    }
    Eigen::Matrix3d kmat;
    kmat << k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1;
    Eigen::Isometry3d T_camN_from_cam0 = Eigen::Isometry3d::Identity();
    T_camN_from_cam0.translation() = kmat.inverse() * Eigen::Vector3d(P[3], P[7], P[11]);
    sensor.T_ego_from_cam = T_ego_from_cam0 * T_camN_from_cam0.inverse();
    CamFiles cf{static_cast<int>(log.cameras.size()), {}};
    for (size_t i = 0; i < files->size(); ++i) cf.by_index[indices[i]] = (*files)[i];
    cam_files.push_back(std::move(cf));
    log.cameras.push_back(sensor);
  }
  if (log.cameras.empty()) {
    return absl::NotFoundError(absl::StrCat(sequence_dir, ": no image_0..3 or image_l/r with .png files"));
  }

  std::map<int, std::string> velo;
  if (fs::is_directory(seq / "velodyne")) {
    auto it = calib->find("Tr");
    if (it == calib->end()) return absl::InvalidArgumentError(absl::StrCat(calib_path, ": velodyne/ present but no Tr"));
    absl::StatusOr<Eigen::Isometry3d> T_cam0_from_velo =
        RigidFrom3x4(it->second.p, absl::StrCat(calib_path, ": line ", it->second.line, ": Tr"));
    if (!T_cam0_from_velo.ok()) return T_cam0_from_velo.status();
    std::vector<int> indices;
    absl::StatusOr<std::vector<std::string>> files = ListNumberedFiles((seq / "velodyne").string(), ".bin", &indices);
    if (!files.ok()) return files.status();
    for (size_t i = 0; i < files->size(); ++i) velo[indices[i]] = (*files)[i];
    if (!velo.empty()) log.lidars.push_back({"velodyne", T_ego_from_cam0 * (*T_cam0_from_velo)});
  }

  // Frame list from the first camera; times from times.txt.
  const std::map<int, std::string>& reference = cam_files.front().by_index;
  std::vector<int64_t> times;
  const std::string times_path = (seq / "times.txt").string();
  if (fs::exists(times_path)) {
    absl::StatusOr<std::vector<std::string>> lines = ReadLines(times_path);
    if (!lines.ok()) return lines.status();
    for (size_t i = 0; i < lines->size(); ++i) {
      if (IsBlankOrComment((*lines)[i])) continue;
      absl::StatusOr<std::vector<double>> v = ParseNumbers((*lines)[i], times_path, static_cast<int>(i + 1), 1);
      if (!v.ok()) return v.status();
      if (!std::isfinite((*v)[0])) return absl::InvalidArgumentError(absl::StrCat(times_path, ": line ", i + 1, ": non-finite time"));
      times.push_back(std::llround((*v)[0] * 1e6));
    }
  } else {
    log.problems.push_back(absl::StrCat(times_path, ": missing; 10 Hz assumed (time_us = frame * 100000)"));
  }

  std::vector<Eigen::Isometry3d> poses;
  const std::string poses_path = (seq / "poses.txt").string();
  if (fs::exists(poses_path)) {
    absl::StatusOr<std::vector<Eigen::Isometry3d>> p = ReadPosesFile(poses_path);
    if (!p.ok()) return p.status();
    poses = *std::move(p);
    log.pose_source = "poses.txt";
  } else {
    return absl::NotFoundError(absl::StrCat(poses_path, ": no such file (camera-only sequences need poses)"));
  }
  if (poses.size() != reference.size()) {
    log.problems.push_back(absl::StrCat(poses_path, ": ", poses.size(), " poses for ", reference.size(),
                                        " images; frames without a pose skipped"));
  }
  const Eigen::Isometry3d T_cam0_from_ego = T_ego_from_cam0.inverse();
  const Eigen::Isometry3d T_first_inv = poses.front().inverse();
  std::vector<int> skipped;
  for (const auto& [index, path] : reference) {
    if (index >= static_cast<int>(poses.size())) {
      skipped.push_back(index);
      continue;
    }
    Frame frame;
    frame.source_index = index;
    if (index < static_cast<int>(times.size())) {
      frame.time_us = times[index];
    } else {
      if (!times.empty()) {
        log.problems.push_back(absl::StrCat(times_path, ": no time for frame ", index, "; frame skipped"));
        continue;
      }
      frame.time_us = index * kAssumedFrameUs;
    }
    frame.T_world_from_ego = T_ego_from_cam0 * T_first_inv * poses[index] * T_cam0_from_ego;
    for (const CamFiles& cf : cam_files) {
      if (auto it = cf.by_index.find(index); it != cf.by_index.end()) {
        frame.cameras.push_back({cf.slot, frame.time_us, it->second});
      }
    }
    if (auto it = velo.find(index); it != velo.end()) frame.lidars.push_back({0, frame.time_us, it->second});
    log.frames.push_back(std::move(frame));
  }
  if (!skipped.empty()) {
    log.problems.push_back(absl::StrCat(skipped.size(), " frame(s) without a pose skipped: ",
                                        skipped.front(), skipped.size() > 1 ? absl::StrCat("-", skipped.back()) : ""));
  }
  if (log.frames.empty()) return absl::InvalidArgumentError(absl::StrCat(sequence_dir, ": no posed frame"));
  return log;
}

}  // namespace streetsim
