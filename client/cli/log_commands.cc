// streetsim log info | preview | poses | camera | tracks: inspecting driving logs.
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "client/cli/args.h"
#include "client/cli/camera_json.h"
#include "client/cli/commands.h"
#include "nlohmann/json.hpp"
#include "scene/common/checked_file.h"
#include "scene/init/lidar_accumulation.h"
#include "scene/init/moving_objects.h"
#include "scene/log/lidar_odometry.h"
#include "scene/log/open_log.h"
#include "scene/log/poses_file.h"
#include "scene/log/undistort.h"

namespace streetsim {
namespace {

int FailLog(const std::string& command, int code, const absl::Status& status) {
  return ReportFailure("log " + command, code, status);
}

// Reading a log fails for bad input (2) unless the machine itself failed (1).
int ExitCodeForLog(const absl::Status& s) {
  return absl::IsInternal(s) || absl::IsResourceExhausted(s) || absl::IsUnknown(s) ? 1 : 2;
}

absl::StatusOr<std::string> OnePath(const ParsedArgs& args) {
  if (args.positional().size() != 1) return absl::InvalidArgumentError("expects exactly one log PATH");
  return args.positional()[0];
}

// --frames A:B[:S]; every frame when absent.
absl::StatusOr<FrameRange> FramesFlag(const ParsedArgs& args) {
  if (auto f = args.Get("frames")) return ParseFrameRange(*f);
  return FrameRange{};
}

absl::StatusOr<int> FrameFlag(const ParsedArgs& args, const DriveLog& log) {
  const std::string text = args.Get("frame").value_or("0");
  int frame;
  if (!absl::SimpleAtoi(text, &frame) || frame < 0 || frame >= static_cast<int>(log.frames.size())) {
    return absl::OutOfRangeError(absl::StrCat("--frame ", text, " is not in 0..", log.frames.size() - 1));
  }
  return frame;
}

absl::StatusOr<const CameraObservation*> CameraFlag(const ParsedArgs& args, const DriveLog& log, const Frame& frame) {
  if (frame.cameras.empty()) return absl::FailedPreconditionError("the frame has no camera image");
  if (!args.Has("camera")) return &frame.cameras[0];
  const std::string name = *args.Get("camera");
  for (const CameraObservation& obs : frame.cameras) {
    if (log.cameras[obs.camera].name == name) return &obs;
  }
  return absl::InvalidArgumentError(absl::StrCat("--camera ", name, ": not in this frame"));
}

std::string FormatUnixUs(int64_t us) {
  const std::time_t s = static_cast<std::time_t>(us / 1'000'000);
  std::tm tm;
  gmtime_r(&s, &tm);
  char buf[64];
  std::strftime(buf, sizeof(buf), "%Y-%m-%d %H:%M:%S", &tm);
  char frac[16];
  std::snprintf(frac, sizeof(frac), ".%06lld UTC", static_cast<long long>(us % 1'000'000));
  return std::string(buf) + frac;
}

std::string Translation(const Eigen::Isometry3d& t) {
  char buf[96];
  std::snprintf(buf, sizeof(buf), "(%.3f, %.3f, %.3f) m", t.translation().x(), t.translation().y(), t.translation().z());
  return buf;
}

int Info(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, {});
  if (!args.ok()) return FailLog("info", 2, args.status());
  absl::StatusOr<std::string> path = OnePath(*args);
  if (!path.ok()) return FailLog("info", 2, path.status());
  absl::StatusOr<DriveLog> log = OpenLog(*path);
  if (!log.ok()) return FailLog("info", ExitCodeForLog(log.status()), log.status());
  std::printf("log: %s\nformat: %s\nposes: %s\n", log->root.c_str(), log->format.c_str(), log->pose_source.c_str());
  std::printf("frames: %zu (source frames %d..%d)\n", log->frames.size(), log->frames.front().source_index,
              log->frames.back().source_index);
  std::printf("time span: %.3f s (%s)\n", log->duration_us() * 1e-6,
              log->time_is_absolute ? absl::StrCat("from ", FormatUnixUs(log->frames.front().time_us)).c_str()
                                    : "relative; no timestamps");
  std::printf("distance driven: %.2f m\n", log->distance_m());
  if (log->geo_origin) {
    std::printf("world: ENU at lat %.9f, lon %.9f, alt %.3f m\n", log->geo_origin->latitude_deg,
                log->geo_origin->longitude_deg, log->geo_origin->altitude_m);
  } else {
    std::printf("world: %s\n", log->format == "colmap" ? "the COLMAP model's frame" : "ego frame of the first frame");
  }
  std::printf("cameras: %zu\n", log->cameras.size());
  bool rig_has_colour = false;
  for (const CameraSensor& c : log->cameras) rig_has_colour = rig_has_colour || c.colour;
  for (const CameraSensor& c : log->cameras) {
    const CameraIntrinsics& k = c.intrinsics;
    // How `streetsim train` uses it by default (docs/training.md "Grayscale cameras").
    const char* trains = c.colour          ? "trains in colour"
                         : rig_has_colour ? "trains on luminance beside the colour cameras"
                                          : "trains as it is (no colour camera)";
    std::printf("  %s: %dx%d %s (%s), fx %.2f fy %.2f cx %.2f cy %.2f, %s, T_ego_from_cam t = %s\n", c.name.c_str(),
                k.width, k.height, c.colour ? "colour" : "grayscale", trains, k.fx, k.fy, k.cx, k.cy,
                DistortionModelName(k.model), Translation(c.T_ego_from_cam).c_str());
  }
  std::printf("lidars: %zu\n", log->lidars.size());
  for (const LidarSensor& l : log->lidars) {
    std::printf("  %s: T_ego_from_lidar t = %s\n", l.name.c_str(), Translation(l.T_ego_from_lidar).c_str());
  }
  if (!log->sparse_points.empty()) std::printf("sparse points: %zu\n", log->sparse_points.size());
  std::printf("problems: %zu\n", log->problems.size());
  for (const std::string& p : log->problems) std::printf("  - %s\n", p.c_str());
  return 0;
}

absl::Status WritePngAtomically(const std::string& path, const cv::Mat& bgr) {
  const std::filesystem::path target(path);
  const std::filesystem::path dir = target.has_parent_path() ? target.parent_path() : ".";
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) {
    return absl::NotFoundError(absl::StrCat(path, ": directory ", dir.string(), " does not exist"));
  }
  const std::filesystem::path tmp = dir / absl::StrCat(".", target.stem().string(), ".tmp", getpid(), ".png");
  bool ok = false;
  try {
    ok = cv::imwrite(tmp.string(), bgr);
  } catch (const cv::Exception& e) {
    ok = false;
  }
  if (!ok) {
    std::filesystem::remove(tmp, ec);
    return absl::PermissionDeniedError(absl::StrCat(path, ": cannot write"));
  }
  std::filesystem::rename(tmp, target, ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(path, ": cannot rename into place"));
  return absl::OkStatus();
}

int Preview(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, {{"frame"}, {"out"}, {"camera"}, {"max-depth"}});
  if (!args.ok()) return FailLog("preview", 2, args.status());
  absl::StatusOr<std::string> path = OnePath(*args);
  if (!path.ok()) return FailLog("preview", 2, path.status());
  absl::StatusOr<std::string> out = args->Required("out");
  if (!out.ok()) return FailLog("preview", 2, out.status());
  if (std::filesystem::path(*out).extension() != ".png") {
    return FailLog("preview", 2, absl::InvalidArgumentError(absl::StrCat("--out ", *out, ": must be a .png")));
  }
  double max_depth = 50;
  if (auto d = args->Get("max-depth"); d && (!absl::SimpleAtod(*d, &max_depth) || !(max_depth > 0))) {
    return FailLog("preview", 2, absl::InvalidArgumentError("--max-depth must be a positive number of metres"));
  }
  absl::StatusOr<DriveLog> log = OpenLog(*path);
  if (!log.ok()) return FailLog("preview", ExitCodeForLog(log.status()), log.status());
  absl::StatusOr<int> frame_index = FrameFlag(*args, *log);
  if (!frame_index.ok()) return FailLog("preview", 2, frame_index.status());
  const Frame& frame = log->frames[*frame_index];
  absl::StatusOr<const CameraObservation*> obs = CameraFlag(*args, *log, frame);
  if (!obs.ok()) return FailLog("preview", 2, obs.status());
  const CameraSensor& cam = log->cameras[(*obs)->camera];
  absl::StatusOr<cv::Mat> image = LoadImageRgb((*obs)->path);
  if (!image.ok()) return FailLog("preview", 2, image.status());

  // Points to draw, in the camera frame: the frame's LiDAR scan, else the log's sparse points.
  std::vector<Eigen::Vector3d> points_cam;
  if (!frame.lidars.empty()) {
    absl::StatusOr<LidarScan> scan = LoadLidarScan(frame.lidars[0].path);
    if (!scan.ok()) return FailLog("preview", 2, scan.status());
    const Eigen::Isometry3d T = cam.T_ego_from_cam.inverse() * log->lidars[frame.lidars[0].lidar].T_ego_from_lidar;
    for (const Eigen::Vector3f& p : scan->points) points_cam.push_back(T * p.cast<double>());
  } else if (!log->sparse_points.empty()) {
    const Eigen::Isometry3d T = WorldFromCamera(*log, frame, **obs).inverse();
    for (const Eigen::Vector3d& p : log->sparse_points) points_cam.push_back(T * p);
  } else {
    return FailLog("preview", 2, absl::FailedPreconditionError(absl::StrCat(*path, ": log has no LiDAR and no sparse points to project")));
  }
  cv::Mat bgr;
  cv::cvtColor(*image, bgr, cv::COLOR_RGB2BGR);
  // Far points first so near ones stay on top.
  std::sort(points_cam.begin(), points_cam.end(), [](const auto& a, const auto& b) { return a.z() > b.z(); });
  cv::Mat lut(1, 256, CV_8UC1);
  for (int i = 0; i < 256; ++i) lut.at<uint8_t>(i) = static_cast<uint8_t>(i);
  cv::Mat colours;
  cv::applyColorMap(lut, colours, cv::COLORMAP_JET);  // index 0 blue .. 255 red
  size_t drawn = 0;
  for (const Eigen::Vector3d& p : points_cam) {
    Eigen::Vector2d uv;
    if (p.z() < 0.5 || !ProjectToPixel(cam.intrinsics, p, &uv)) continue;
    if (uv.x() < 0 || uv.y() < 0 || uv.x() >= bgr.cols || uv.y() >= bgr.rows) continue;
    const int index = 255 - static_cast<int>(std::clamp(p.z() / max_depth, 0.0, 1.0) * 255);  // near = red
    const cv::Vec3b c = colours.at<cv::Vec3b>(0, index);
    cv::circle(bgr, cv::Point(static_cast<int>(uv.x()), static_cast<int>(uv.y())), 1, cv::Scalar(c[0], c[1], c[2]), -1);
    ++drawn;
  }
  if (absl::Status s = WritePngAtomically(*out, bgr); !s.ok()) return FailLog("preview", 1, s);
  std::fprintf(stderr, "streetsim log preview: frame %d (%s), %zu points drawn, red = near, blue >= %.0f m\n",
               *frame_index, cam.name.c_str(), drawn, max_depth);
  return 0;
}

int Poses(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, {{"from-lidar", false}, {"frames"}, {"out"}});
  if (!args.ok()) return FailLog("poses", 2, args.status());
  absl::StatusOr<std::string> path = OnePath(*args);
  if (!path.ok()) return FailLog("poses", 2, path.status());
  absl::StatusOr<FrameRange> frames_flag = FramesFlag(*args);
  if (!frames_flag.ok()) return FailLog("poses", 2, frames_flag.status());
  const FrameRange range = *frames_flag;
  absl::StatusOr<DriveLog> log = OpenLog(*path);
  if (!log.ok()) return FailLog("poses", ExitCodeForLog(log.status()), log.status());
  std::vector<int> frames = range.Select(*log);
  if (frames.size() < 2) return FailLog("poses", 2, absl::InvalidArgumentError("--frames selects fewer than 2 frames"));
  std::vector<Eigen::Isometry3d> reference;
  for (int f : frames) reference.push_back(log->frames[f].T_world_from_ego);
  std::vector<Eigen::Isometry3d> poses = reference;
  std::string comment = absl::StrCat("T_world_from_ego per frame (", log->pose_source, ")");
  if (args->Has("from-lidar")) {
    if (range.stride != 1) return FailLog("poses", 2, absl::InvalidArgumentError("--from-lidar needs consecutive frames (stride 1)"));
    LidarOdometryOptions options;
    options.first_frame = frames.front();
    options.last_frame = frames.back() + 1;
    absl::StatusOr<LidarOdometryResult> odo = RunLidarOdometry(*log, options);
    if (!odo.ok()) return FailLog("poses", absl::IsFailedPrecondition(odo.status()) ? 2 : 1, odo.status());
    poses = odo->T_world_from_ego;
    comment = "T_world_from_ego per frame from LiDAR odometry (world = ego at the first frame)";
    const TrajectoryComparison c = CompareTrajectories(poses, reference);
    std::printf("lidar odometry: %zu frames, %.1f ms per scan\n", poses.size(), odo->ms_per_scan);
    std::printf("against %s: %.2f m driven, end error %.3f m, max %.3f m, end rotation %.2f deg, "
                "drift %.2f m per 100 m%s, per-frame %.3f m / %.3f deg\n",
                log->pose_source.c_str(), c.reference_distance_m, c.final_translation_error_m,
                c.max_translation_error_m, c.final_rotation_error_deg, c.drift_percent,
                c.reference_distance_m < 100 ? " (extrapolated from a shorter drive)" : "",
                c.mean_relative_translation_error_m, c.mean_relative_rotation_error_deg);
    for (const std::string& p : odo->problems) std::printf("  - %s\n", p.c_str());
  } else {
    std::printf("%zu poses from %s, %.2f m driven\n", poses.size(), log->pose_source.c_str(), log->distance_m());
  }
  if (auto out = args->Get("out")) {
    if (absl::Status s = WritePosesFile(*out, poses, comment); !s.ok()) return FailLog("poses", 1, s);
  }
  return 0;
}

int Camera(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, {{"frame"}, {"out"}, {"camera"}});
  if (!args.ok()) return FailLog("camera", 2, args.status());
  absl::StatusOr<std::string> path = OnePath(*args);
  if (!path.ok()) return FailLog("camera", 2, path.status());
  absl::StatusOr<std::string> out = args->Required("out");
  if (!out.ok()) return FailLog("camera", 2, out.status());
  absl::StatusOr<DriveLog> log = OpenLog(*path);
  if (!log.ok()) return FailLog("camera", ExitCodeForLog(log.status()), log.status());
  absl::StatusOr<int> frame_index = FrameFlag(*args, *log);
  if (!frame_index.ok()) return FailLog("camera", 2, frame_index.status());
  const Frame& frame = log->frames[*frame_index];
  absl::StatusOr<const CameraObservation*> obs = CameraFlag(*args, *log, frame);
  if (!obs.ok()) return FailLog("camera", 2, obs.status());
  const CameraIntrinsics& k = log->cameras[(*obs)->camera].intrinsics;
  PinholeCamera camera;
  camera.width = k.width;
  camera.height = k.height;
  camera.fx = k.fx;
  camera.fy = k.fy;
  camera.cx = k.cx;
  camera.cy = k.cy;
  camera.T_world_from_cam = WorldFromCamera(*log, frame, **obs);
  std::ofstream f(*out);
  f << CameraToJson(camera);
  if (!f.good()) return FailLog("camera", 1, absl::PermissionDeniedError(absl::StrCat(*out, ": cannot write")));
  return 0;
}

// The log's moving objects, followed in its LiDAR alone (scene/init/moving_objects.h).
int Tracks(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args =
      ParsedArgs::Parse(argv, {{"frames"}, {"min-scans"}, {"min-displacement-m"}, {"json"}});
  if (!args.ok()) return FailLog("tracks", 2, args.status());
  absl::StatusOr<std::string> path = OnePath(*args);
  if (!path.ok()) return FailLog("tracks", 2, path.status());
  MovingObjectOptions options;
  absl::StatusOr<FrameRange> frames_flag = FramesFlag(*args);
  if (!frames_flag.ok()) return FailLog("tracks", 2, frames_flag.status());
  options.frames = *frames_flag;
  if (options.frames.stride != 1) {
    return FailLog("tracks", 2, absl::InvalidArgumentError("--frames: tracking needs consecutive frames (stride 1)"));
  }
  int min_scans = 5;
  double min_displacement_m = 1.0;
  if (auto v = args->Get("min-scans"); v && (!absl::SimpleAtoi(*v, &min_scans) || min_scans < 1)) {
    return FailLog("tracks", 2, absl::InvalidArgumentError("--min-scans: a whole number >= 1"));
  }
  if (auto v = args->Get("min-displacement-m");
      v && (!absl::SimpleAtod(*v, &min_displacement_m) || !(min_displacement_m >= 0 && min_displacement_m < 1e4))) {
    return FailLog("tracks", 2, absl::InvalidArgumentError("--min-displacement-m: metres, 0 .. 10000"));
  }
  absl::StatusOr<DriveLog> log = OpenLog(*path);
  if (!log.ok()) return FailLog("tracks", ExitCodeForLog(log.status()), log.status());
  absl::StatusOr<MovingObjects> objects = TrackMovingObjects(*log, options);
  if (!objects.ok()) return FailLog("tracks", ExitCodeForLog(objects.status()), objects.status());
  std::vector<const MovingObjectTrack*> shown;
  for (const MovingObjectTrack& t : objects->tracks) {
    if (static_cast<int>(t.observations.size()) >= min_scans && t.NetDisplacementM() >= min_displacement_m) {
      shown.push_back(&t);
    }
  }
  std::printf("moving objects, LiDAR only: %d scans, %zu tracks, %zu followed for >= %d scans and moved >= %.2f m\n",
              objects->frames_used, objects->tracks.size(), shown.size(), min_scans, min_displacement_m);
  std::printf(
      "| id | frames | scans | moved (m) | path (m) | mean speed (m/s) | first seen at x, y (ego, m) | "
      "points |\n|---|---|---|---|---|---|---|---|\n");
  for (const MovingObjectTrack* t : shown) {
    const ObjectObservation& a = t->observations.front();
    const ObjectObservation& b = t->observations.back();
    const Eigen::Vector3d c = log->frames[a.frame].T_world_from_ego.inverse() * a.centroid_world;
    const double span_s = (b.time_us - a.time_us) * 1e-6;
    std::printf("| %d | %d-%d | %zu | %.2f | %.2f | %.2f | %.1f, %.1f | %d |\n", t->id, a.frame, b.frame,
                t->observations.size(), t->NetDisplacementM(), t->PathLengthM(),
                span_s > 0 ? t->PathLengthM() / span_s : 0.0, c.x(), c.y(), a.num_points);
  }
  if (auto out = args->Get("json")) {
    nlohmann::json j;
    j["log"] = log->root;
    j["frames_used"] = objects->frames_used;
    j["min_scans"] = min_scans;
    j["min_displacement_m"] = min_displacement_m;
    j["tracks"] = nlohmann::json::array();
    for (const MovingObjectTrack* t : shown) {
      nlohmann::json jt;
      jt["id"] = t->id;
      jt["net_displacement_m"] = t->NetDisplacementM();
      jt["path_length_m"] = t->PathLengthM();
      jt["observations"] = nlohmann::json::array();
      for (const ObjectObservation& ob : t->observations) {
        const Eigen::Vector3d tr = ob.T_world_motion.translation();
        const Eigen::Matrix3d r = ob.T_world_motion.linear();
        jt["observations"].push_back(
            {{"frame", ob.frame},
             {"time_us", ob.time_us},
             {"centroid_world", {ob.centroid_world.x(), ob.centroid_world.y(), ob.centroid_world.z()}},
             {"T_world_motion_translation", {tr.x(), tr.y(), tr.z()}},
             {"T_world_motion_rotation",
              {r(0, 0), r(0, 1), r(0, 2), r(1, 0), r(1, 1), r(1, 2), r(2, 0), r(2, 1), r(2, 2)}},
             {"num_points", ob.num_points},
             {"num_dynamic", ob.num_dynamic},
             {"icp_rms_m", ob.icp_rms_m}});
      }
      j["tracks"].push_back(std::move(jt));
    }
    if (absl::Status s = checked_file::WriteAtomically(*out, j.dump(1) + "\n"); !s.ok()) return FailLog("tracks", 1, s);
  }
  return 0;
}

}  // namespace

int RunLogCommand(const std::vector<std::string>& args) {
  if (args.empty()) {
    std::fprintf(stderr, "streetsim log: expects a subcommand: info, preview, poses, camera or tracks\n");
    return 2;
  }
  const std::vector<std::string> rest(args.begin() + 1, args.end());
  if (args[0] == "info") return Info(rest);
  if (args[0] == "preview") return Preview(rest);
  if (args[0] == "poses") return Poses(rest);
  if (args[0] == "camera") return Camera(rest);
  if (args[0] == "tracks") return Tracks(rest);
  std::fprintf(stderr, "streetsim log: unknown subcommand '%s' (info, preview, poses, camera, tracks)\n",
               args[0].c_str());
  return 2;
}

}  // namespace streetsim
