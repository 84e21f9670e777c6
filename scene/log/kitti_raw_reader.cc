#include "scene/log/kitti_raw_reader.h"

#include <cmath>
#include <filesystem>
#include <map>
#include <optional>
#include <set>

#include <opencv2/imgcodecs.hpp>

#include "absl/strings/str_cat.h"
#include "scene/log/lidar_odometry.h"
#include "scene/log/oxts.h"
#include "scene/log/poses_file.h"
#include "scene/log/text_util.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;

std::string CameraDirName(int cam) { return absl::StrCat("image_0", cam); }

std::string FindCalibDir(const fs::path& drive) {
  for (const fs::path& dir : {drive, drive.parent_path()}) {
    if (fs::exists(dir / "calib_cam_to_cam.txt") || fs::exists(dir / "calib_velo_to_cam.txt")) {
      return dir.string();
    }
  }
  return drive.parent_path().string();
}

absl::StatusOr<Eigen::Isometry3d> ReadRt(const CalibFile& calib) {
  absl::StatusOr<std::vector<double>> r = calib.Get("R", 9);
  if (!r.ok()) return r.status();
  absl::StatusOr<std::vector<double>> t = calib.Get("T", 3);
  if (!t.ok()) return t.status();
  return RigidFromRowMajor(r->data(), Eigen::Vector3d((*t)[0], (*t)[1], (*t)[2]),
                           absl::StrCat(calib.path, ": line ", calib.entries.at("R").line, ": R"));
}

struct SensorFiles {
  std::map<int, std::string> by_index;
  std::vector<int64_t> times;  // by file index when timestamps.txt exists
};

absl::StatusOr<SensorFiles> ListSensor(const fs::path& sensor_dir, const std::string& ext) {
  SensorFiles files;
  std::vector<int> indices;
  absl::StatusOr<std::vector<std::string>> paths = ListNumberedFiles((sensor_dir / "data").string(), ext, &indices);
  if (!paths.ok()) return paths.status();
  for (size_t i = 0; i < paths->size(); ++i) files.by_index[indices[i]] = (*paths)[i];
  const fs::path ts = sensor_dir / "timestamps.txt";
  if (fs::exists(ts)) {
    absl::StatusOr<std::vector<int64_t>> times = ReadKittiTimestamps(ts.string());
    if (!times.ok()) return times.status();
    files.times = *std::move(times);
  }
  return files;
}

}  // namespace

absl::StatusOr<KittiRawCalibration> ReadKittiRawCalibration(const std::string& calib_dir) {
  const fs::path dir(calib_dir);
  KittiRawCalibration out;
  absl::StatusOr<CalibFile> velo_to_cam = ReadCalibFile((dir / "calib_velo_to_cam.txt").string());
  if (!velo_to_cam.ok()) return velo_to_cam.status();
  absl::StatusOr<CalibFile> imu_to_velo = ReadCalibFile((dir / "calib_imu_to_velo.txt").string());
  if (!imu_to_velo.ok()) return imu_to_velo.status();
  absl::StatusOr<CalibFile> cam_to_cam = ReadCalibFile((dir / "calib_cam_to_cam.txt").string());
  if (!cam_to_cam.ok()) return cam_to_cam.status();

  absl::StatusOr<Eigen::Isometry3d> T_cam0_from_velo = ReadRt(*velo_to_cam);
  if (!T_cam0_from_velo.ok()) return T_cam0_from_velo.status();
  absl::StatusOr<Eigen::Isometry3d> T_velo_from_imu = ReadRt(*imu_to_velo);
  if (!T_velo_from_imu.ok()) return T_velo_from_imu.status();
  out.T_ego_from_velo = T_velo_from_imu->inverse();

  absl::StatusOr<std::vector<double>> r_rect = cam_to_cam->Get("R_rect_00", 9);
  if (!r_rect.ok()) return r_rect.status();
  absl::StatusOr<Eigen::Isometry3d> T_rect0_from_cam0 = RigidFromRowMajor(
      r_rect->data(), Eigen::Vector3d::Zero(),
      absl::StrCat(cam_to_cam->path, ": line ", cam_to_cam->entries.at("R_rect_00").line, ": R_rect_00"));
  if (!T_rect0_from_cam0.ok()) return T_rect0_from_cam0.status();

  for (int cam = 0; cam < 4; ++cam) {
    const std::string p_key = absl::StrCat("P_rect_0", cam), s_key = absl::StrCat("S_rect_0", cam);
    absl::StatusOr<std::vector<double>> p = cam_to_cam->Get(p_key, 12);
    if (!p.ok()) return p.status();
    absl::StatusOr<std::vector<double>> s = cam_to_cam->Get(s_key, 2);
    if (!s.ok()) return s.status();
    const std::string where = absl::StrCat(cam_to_cam->path, ": line ", cam_to_cam->entries.at(p_key).line, ": ", p_key);
    const std::vector<double>& P = *p;
    CameraIntrinsics& k = out.intrinsics[cam];
    k.width = static_cast<int>(std::lround((*s)[0]));
    k.height = static_cast<int>(std::lround((*s)[1]));
    k.fx = P[0];
    k.fy = P[5];
    k.cx = P[2];
    k.cy = P[6];
    if (!(k.fx > 0) || !(k.fy > 0) || P[1] != 0 || P[4] != 0 || P[8] != 0 || P[9] != 0 || P[10] != 1) {
      return absl::InvalidArgumentError(absl::StrCat(where, ": not a rectified projection K [I | t]"));
    }
    if (k.width <= 0 || k.height <= 0 || k.width > 8192 || k.height > 8192) {
      return absl::InvalidArgumentError(absl::StrCat(cam_to_cam->path, ": line ",
                                                     cam_to_cam->entries.at(s_key).line, ": ", s_key,
                                                     ": bad image size"));
    }
    Eigen::Matrix3d kmat;
    kmat << k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1;
    // P = K [I | t]: t = K^-1 p4 (the stereo baseline plus the small residual offsets).
    Eigen::Isometry3d T_camN_from_rect0 = Eigen::Isometry3d::Identity();
    T_camN_from_rect0.translation() = kmat.inverse() * Eigen::Vector3d(P[3], P[7], P[11]);
    out.T_cam_from_velo[cam] = T_camN_from_rect0 * (*T_rect0_from_cam0) * (*T_cam0_from_velo);
  }
  return out;
}

namespace {

// What a drive directory holds: its cameras, LiDAR scans and OXTS track.
struct DriveSensors {
  std::map<int, SensorFiles> cams;  // by camera number
  std::optional<SensorFiles> velo;
  std::optional<OxtsTrack> oxts;
};

absl::StatusOr<DriveSensors> ListDriveSensors(const fs::path& drive, DriveLog& log) {
  DriveSensors s;
  for (int cam = 0; cam < 4; ++cam) {
    if (!fs::is_directory(drive / CameraDirName(cam) / "data")) continue;
    absl::StatusOr<SensorFiles> files = ListSensor(drive / CameraDirName(cam), ".png");
    if (!files.ok()) return files.status();
    if (files->by_index.empty()) {
      log.problems.push_back(absl::StrCat(CameraDirName(cam), "/data: no images; camera ignored"));
      continue;
    }
    s.cams[cam] = *std::move(files);
  }
  if (fs::is_directory(drive / "velodyne_points" / "data")) {
    absl::StatusOr<SensorFiles> files = ListSensor(drive / "velodyne_points", ".bin");
    if (!files.ok()) return files.status();
    if (!files->by_index.empty()) s.velo = *std::move(files);
  }
  if (fs::is_directory(drive / "oxts")) {
    absl::StatusOr<OxtsTrack> track = ReadOxtsDirectory((drive / "oxts").string());
    if (!track.ok()) return track.status();
    s.oxts = *std::move(track);
    log.problems.insert(log.problems.end(), s.oxts->problems.begin(), s.oxts->problems.end());
  }
  return s;
}

// log.cameras and log.lidars placed on the ego by `calib`, each camera's calibration checked
// against its first image. Returns camera number -> index in log.cameras.
absl::StatusOr<std::map<int, int>> PlaceSensors(const fs::path& drive, const DriveSensors& s,
                                                const KittiRawCalibration& calib, DriveLog& log) {
  std::map<int, int> cam_slot;
  for (const auto& [cam, files] : s.cams) {
    CameraSensor sensor;
    sensor.name = CameraDirName(cam);
    sensor.intrinsics = calib.intrinsics[cam];
    sensor.T_ego_from_cam = calib.T_ego_from_velo * calib.T_cam_from_velo[cam].inverse();
    sensor.colour = cam >= 2;
    // The calibration must describe the images actually stored (a wrong day's calib would not).
    const std::string& first = files.by_index.begin()->second;
    cv::Mat probe;
    try {
      probe = cv::imread(first, cv::IMREAD_UNCHANGED);
    } catch (const cv::Exception&) {
    }
    if (probe.empty()) return absl::DataLossError(absl::StrCat(first, ": cannot decode image"));
    if (probe.cols != sensor.intrinsics.width || probe.rows != sensor.intrinsics.height) {
      return absl::InvalidArgumentError(absl::StrCat(
          first, ": image is ", probe.cols, "x", probe.rows, " but S_rect_0", cam, " in ",
          FindCalibDir(drive), "/calib_cam_to_cam.txt says ", sensor.intrinsics.width, "x",
          sensor.intrinsics.height));
    }
    cam_slot[cam] = static_cast<int>(log.cameras.size());
    log.cameras.push_back(sensor);
  }
  if (s.velo) log.lidars.push_back({"velodyne_points", calib.T_ego_from_velo});
  return cam_slot;
}

// Every frame index any sensor has; a sensor that misses some is noted in log.problems.
std::set<int> FrameIndices(const DriveSensors& s, DriveLog& log) {
  std::set<int> indices;
  for (const auto& [cam, files] : s.cams) for (const auto& [i, p] : files.by_index) indices.insert(i);
  if (s.velo) for (const auto& [i, p] : s.velo->by_index) indices.insert(i);
  if (s.oxts) indices.insert(s.oxts->source_index.begin(), s.oxts->source_index.end());
  for (const auto& [cam, files] : s.cams) {
    if (files.by_index.size() != indices.size()) {
      log.problems.push_back(absl::StrCat(CameraDirName(cam), ": ", files.by_index.size(),
                                          " images for ", indices.size(), " frames"));
    }
  }
  if (s.velo && s.velo->by_index.size() != indices.size()) {
    log.problems.push_back(absl::StrCat("velodyne_points: ", s.velo->by_index.size(), " scans for ",
                                        indices.size(), " frames"));
  }
  return indices;
}

std::optional<int64_t> SensorTime(const SensorFiles& f, int index) {
  if (index < static_cast<int>(f.times.size())) return f.times[index];
  return std::nullopt;
}

// log.frames, one per index, timed by OXTS, else the first sensor with timestamps.txt, else 10 Hz.
void AddFrames(const std::string& drive_dir, const DriveSensors& s, const std::set<int>& indices,
               const std::map<int, int>& cam_slot, DriveLog& log) {
  std::map<int, int64_t> oxts_time;
  if (s.oxts && s.oxts->time_is_absolute) {
    for (size_t i = 0; i < s.oxts->source_index.size(); ++i) oxts_time[s.oxts->source_index[i]] = s.oxts->time_us[i];
  }
  bool any_absolute = !oxts_time.empty() || (s.velo && !s.velo->times.empty());
  for (const auto& [cam, files] : s.cams) any_absolute = any_absolute || !files.times.empty();
  log.time_is_absolute = any_absolute;
  if (!any_absolute) {
    log.problems.push_back(absl::StrCat(drive_dir, ": no timestamps.txt; 10 Hz assumed (time_us = frame * 100000)"));
  }
  for (int index : indices) {
    Frame frame;
    frame.source_index = index;
    std::optional<int64_t> t;
    if (auto it = oxts_time.find(index); it != oxts_time.end()) t = it->second;
    for (const auto& [cam, files] : s.cams) if (!t) t = SensorTime(files, index);
    if (!t && s.velo) t = SensorTime(*s.velo, index);
    frame.time_us = t ? *t : index * kAssumedFrameUs;
    for (const auto& [cam, files] : s.cams) {
      auto it = files.by_index.find(index);
      if (it == files.by_index.end()) continue;
      frame.cameras.push_back({cam_slot.at(cam), SensorTime(files, index).value_or(frame.time_us), it->second});
    }
    if (s.velo) {
      if (auto it = s.velo->by_index.find(index); it != s.velo->by_index.end()) {
        frame.lidars.push_back({0, SensorTime(*s.velo, index).value_or(frame.time_us), it->second});
      }
    }
    log.frames.push_back(std::move(frame));
  }
}

fs::path PosesFilePath(const fs::path& drive) {
  return fs::exists(drive / "poses_velo_icp_estimated.txt") ? drive / "poses_velo_icp_estimated.txt"
                                                            : drive / "poses.txt";
}

// kAuto: OXTS, else a poses file, else LiDAR odometry.
PoseSource ResolvePoseSource(PoseSource requested, const fs::path& drive, const DriveSensors& s) {
  if (requested != PoseSource::kAuto) return requested;
  if (s.oxts) return PoseSource::kOxts;
  return fs::exists(PosesFilePath(drive)) ? PoseSource::kPosesFile : PoseSource::kLidarOdometry;
}

// T_world_from_ego by frame index from `source` (resolved: OXTS, a poses file, or LiDAR odometry
// over log.frames); sets log.pose_source and the geo origin.
absl::StatusOr<std::map<int, Eigen::Isometry3d>> PosesByIndex(PoseSource source, const fs::path& drive,
                                                              const DriveSensors& s,
                                                              const KittiRawCalibration& calib,
                                                              size_t num_indices, DriveLog& log) {
  const std::string drive_dir = drive.string();
  std::map<int, Eigen::Isometry3d> pose_by_index;
  const fs::path poses_path = PosesFilePath(drive);
  if (source == PoseSource::kOxts) {
    if (!s.oxts) return absl::NotFoundError(absl::StrCat(drive_dir, ": no oxts directory"));
    log.pose_source = "oxts";
    log.has_gnss = true;
    log.geo_origin = s.oxts->origin;
    for (size_t i = 0; i < s.oxts->source_index.size(); ++i) {
      pose_by_index[s.oxts->source_index[i]] = s.oxts->T_world_from_ego[i];
    }
  } else if (source == PoseSource::kPosesFile) {
    absl::StatusOr<std::vector<Eigen::Isometry3d>> poses = ReadPosesFile(poses_path.string());
    if (!poses.ok()) return poses.status();
    if (!s.velo) return absl::FailedPreconditionError(absl::StrCat(poses_path.string(), ": T_world_from_velo needs the velodyne calibration"));
    log.pose_source = poses_path.filename().string();
    const Eigen::Isometry3d T_velo_from_ego = calib.T_ego_from_velo.inverse();
    for (size_t i = 0; i < poses->size(); ++i) {
      pose_by_index[static_cast<int>(i)] = calib.T_ego_from_velo * (*poses)[i] * T_velo_from_ego;
    }
    if (poses->size() != num_indices) {
      log.problems.push_back(absl::StrCat(poses_path.string(), ": ", poses->size(), " poses for ",
                                          num_indices, " frames"));
    }
  } else {
    if (!s.velo) return absl::NotFoundError(absl::StrCat(drive_dir, ": no oxts, no poses file and no LiDAR: cannot pose the frames"));
    log.problems.push_back(absl::StrCat(drive_dir, ": no oxts and no poses file; poses from LiDAR odometry"));
    absl::StatusOr<LidarOdometryResult> odo = RunLidarOdometry(log);
    if (!odo.ok()) return odo.status();
    log.pose_source = "lidar_odometry";
    for (size_t i = 0; i < odo->frames.size(); ++i) pose_by_index[log.frames[odo->frames[i]].source_index] = odo->T_world_from_ego[i];
    log.problems.insert(log.problems.end(), odo->problems.begin(), odo->problems.end());
  }
  return pose_by_index;
}

// Frames without a pose are dropped, never given a made-up one.
void KeepPosedFrames(const std::map<int, Eigen::Isometry3d>& pose_by_index, DriveLog& log) {
  std::vector<Frame> posed;
  std::vector<int> skipped;
  for (Frame& f : log.frames) {
    auto it = pose_by_index.find(f.source_index);
    if (it == pose_by_index.end()) {
      skipped.push_back(f.source_index);
      continue;
    }
    f.T_world_from_ego = it->second;
    posed.push_back(std::move(f));
  }
  if (!skipped.empty()) {
    log.problems.push_back(absl::StrCat(skipped.size(), " frames without a pose skipped (first: ",
                                        skipped.front(), ")"));
  }
  log.frames = std::move(posed);
}

}  // namespace

absl::StatusOr<DriveLog> ReadKittiRaw(const std::string& drive_dir, const KittiRawOptions& options) {
  const fs::path drive(drive_dir);
  if (!fs::is_directory(drive)) return absl::NotFoundError(absl::StrCat(drive_dir, ": no such directory"));
  DriveLog log;
  log.format = "kitti_raw";
  log.root = drive_dir;
  absl::StatusOr<DriveSensors> sensors = ListDriveSensors(drive, log);
  if (!sensors.ok()) return sensors.status();
  if (sensors->cams.empty() && !sensors->velo && !sensors->oxts) {
    return absl::NotFoundError(absl::StrCat(drive_dir, ": no image_0N, velodyne_points or oxts data"));
  }
  if (sensors->cams.empty() && !sensors->velo) log.format = "kitti_oxts";

  // Calibration (needed only when there are sensors to place).
  KittiRawCalibration calib;
  if (!sensors->cams.empty() || sensors->velo) {
    absl::StatusOr<KittiRawCalibration> c = ReadKittiRawCalibration(FindCalibDir(drive));
    if (!c.ok()) return c.status();
    calib = *std::move(c);
  }
  absl::StatusOr<std::map<int, int>> cam_slot = PlaceSensors(drive, *sensors, calib, log);
  if (!cam_slot.ok()) return cam_slot.status();
  const std::set<int> indices = FrameIndices(*sensors, log);
  AddFrames(drive_dir, *sensors, indices, *cam_slot, log);
  absl::StatusOr<std::map<int, Eigen::Isometry3d>> poses =
      PosesByIndex(ResolvePoseSource(options.pose_source, drive, *sensors), drive, *sensors, calib, indices.size(), log);
  if (!poses.ok()) return poses.status();
  KeepPosedFrames(*poses, log);
  if (log.frames.empty()) return absl::InvalidArgumentError(absl::StrCat(drive_dir, ": no frame has a pose"));
  return log;
}

}  // namespace streetsim
