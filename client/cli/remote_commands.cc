// Subcommands that talk to a streetsim server: scenes, jobs, render --server, replay.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>

#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <opencv2/videoio.hpp>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "client/cli/args.h"
#include "client/cli/camera_json.h"
#include "client/cli/commands.h"
#include "client/cli/image_io.h"
#include "client/cli/replay_scenario.h"
#include "client/cli/train_flags.h"
#include "client/cpp/streetsim_client.h"
#include "scene/common/checked_file.h"
#include "scene/train/config/run_config.h"

namespace streetsim {
namespace {

namespace fs = std::filesystem;
namespace v1 = ::streetsim::v1;
using nlohmann::json;

int FailRemote(const char* command, int code, const absl::Status& status) {
  return ReportFailure(command, code, status);
}

// Bad input from the caller (exit 2) vs. a failure on the way (exit 1).
int CodeFor(const absl::Status& s) {
  switch (s.code()) {
    case absl::StatusCode::kInvalidArgument:
    case absl::StatusCode::kNotFound:
    case absl::StatusCode::kOutOfRange:
    case absl::StatusCode::kAlreadyExists:
    case absl::StatusCode::kUnauthenticated:
    case absl::StatusCode::kPermissionDenied:
      return 2;
    default:
      return 1;
  }
}

const std::vector<FlagSpec> kConnectionFlags = {{"server"}, {"token-file"}, {"tls-ca"}, {"timeout-s"}};

std::vector<FlagSpec> WithConnection(std::vector<FlagSpec> flags) {
  flags.insert(flags.end(), kConnectionFlags.begin(), kConnectionFlags.end());
  return flags;
}

absl::StatusOr<std::unique_ptr<client::Client>> ConnectFromFlags(const ParsedArgs& args) {
  client::ClientOptions o;
  o.target = args.Get("server").value_or("127.0.0.1:50051");
  if (auto f = args.Get("token-file")) {
    std::ifstream in(*f);
    if (!in) return absl::InvalidArgumentError(absl::StrCat("--token-file ", *f, ": cannot open"));
    std::string line;
    std::getline(in, line);
    o.token = std::string(absl::StripAsciiWhitespace(line));
  }
  o.tls_root_cert_file = args.Get("tls-ca").value_or("");
  if (auto t = args.Get("timeout-s")) {
    if (!absl::SimpleAtod(*t, &o.timeout_s) || !(o.timeout_s > 0)) {
      return absl::InvalidArgumentError("--timeout-s takes a positive number of seconds");
    }
  }
  return client::Client::Connect(o);
}

absl::Status WriteFloatImage(const std::string& path, const v1::Image& image) {
  absl::StatusOr<client::DecodedImage> d = client::DecodeImage(image);
  if (!d.ok()) return d.status();
  return WriteFloatTiff(path, d->width, d->height, d->f32);
}

const char* StateName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_QUEUED: return "queued";
    case v1::JOB_STATE_RUNNING: return "running";
    case v1::JOB_STATE_SUCCEEDED: return "succeeded";
    case v1::JOB_STATE_FAILED: return "failed";
    case v1::JOB_STATE_CANCELLED: return "cancelled";
    default: return "unknown";
  }
}

const char* SceneStateName(v1::SceneState s) {
  switch (s) {
    case v1::SCENE_STATE_AVAILABLE: return "available";
    case v1::SCENE_STATE_LOADING: return "loading";
    case v1::SCENE_STATE_READY: return "ready";
    case v1::SCENE_STATE_FAILED: return "failed";
    default: return "unknown";
  }
}

void PrintJob(const v1::Job& j) {
  std::string heldout;
  if (j.heldout().views() > 0) {
    heldout = absl::StrFormat("  held-out %d views: PSNR %.2f dB, SSIM %.4f", j.heldout().views(),
                              j.heldout().psnr_db(), j.heldout().ssim());
    if (j.heldout().psnr_dynamic_db() >= 0) heldout += absl::StrFormat(", PSNR* %.2f dB", j.heldout().psnr_dynamic_db());
  }
  std::printf("%s  %-9s  %-10s  scene %s  log %s  attempts %d%s%s%s\n", j.job_id().c_str(), StateName(j.state()),
              j.progress().stage().c_str(), j.scene_name().c_str(), j.log_path().c_str(), j.attempts(),
              heldout.c_str(), j.error().empty() ? "" : "  error: ", j.error().c_str());
}

void ProgressBar(const v1::Job& j) {
  const int width = 30;
  const int filled = static_cast<int>(std::clamp(j.progress().fraction(), 0.0, 1.0) * width);
  std::fprintf(stderr, "\r[%s%s] %3.0f%%  %-9s stage %-8s  %.1f s  %llu Gaussians", std::string(filled, '#').c_str(),
               std::string(width - filled, '.').c_str(), 100 * j.progress().fraction(), StateName(j.state()),
               j.progress().stage().c_str(), j.progress().elapsed_s(),
               static_cast<unsigned long long>(j.progress().num_gaussians()));
  std::fflush(stderr);
}

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(std::ceil(q * v.size())) - (q > 0 ? 1 : 0))];
}

// A step's images into DIR/frames (named by step and sensor) and each sensor's video; the
// step's record of its frames (file, digest).
absl::StatusOr<json> WriteStepFrames(const v1::StepResponse& r, int k, bool jpeg, const std::string& out_dir,
                                     double fps, std::map<std::string, cv::VideoWriter>* videos) {
  json frames = json::object();
  for (const v1::SensorFrame& f : r.frames()) {
    const std::string name = absl::StrCat("step_", std::string(5 - std::min<size_t>(5, std::to_string(k).size()), '0'),
                                          k, "_", f.sensor_id(), jpeg ? ".jpg" : ".png");
    if (absl::Status s = checked_file::WriteAtomically((fs::path(out_dir) / "frames" / name).string(), f.rgb().data());
        !s.ok()) {
      return s;
    }
    frames[f.sensor_id()] = {{"file", "frames/" + name}, {"digest", f.rgb().digest()}};
    std::vector<uchar> buf(f.rgb().data().begin(), f.rgb().data().end());
    cv::Mat bgr = cv::imdecode(buf, cv::IMREAD_COLOR);
    cv::VideoWriter& vw = (*videos)[f.sensor_id()];
    if (!vw.isOpened() && !bgr.empty()) {
      vw.open((fs::path(out_dir) / (f.sensor_id() + ".avi")).string(), cv::VideoWriter::fourcc('M', 'J', 'P', 'G'),
              fps, bgr.size());
    }
    if (vw.isOpened() && !bgr.empty()) vw.write(bgr);
  }
  return frames;
}

// The session a scenario drives: its scene, step length, start, outputs and sensors.
v1::CreateSessionRequest ScenarioSession(const ReplayScenario& sc, const v1::Scene& info,
                                         std::vector<std::string>* sensor_ids) {
  v1::CreateSessionRequest create;
  create.set_scene(sc.scene);
  create.set_step_dt_us(sc.step_dt_us);
  create.set_start_time_us(sc.start_time_us);
  create.set_seed(sc.seed);
  create.mutable_outputs()->set_rgb(true);
  create.mutable_outputs()->set_rgb_encoding(sc.jpeg ? v1::IMAGE_ENCODING_JPEG : v1::IMAGE_ENCODING_PNG);
  create.mutable_outputs()->set_depth(sc.depth);
  create.mutable_outputs()->set_depth_encoding(v1::DEPTH_ENCODING_PNG16);
  *sensor_ids = sc.sensors;
  if (sensor_ids->empty()) {
    for (const auto& cam : info.rig().cameras()) sensor_ids->push_back(cam.sensor_id());
  }
  for (const std::string& id : *sensor_ids) {
    v1::SensorRequest* s = create.add_sensors();
    s->set_sensor_id(id);
    s->set_width(sc.width);
    s->set_height(sc.height);
  }
  return create;
}

}  // namespace

int RunScenesCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, WithConnection({{"load"}, {"unload"}, {"info"}}));
  if (!args.ok()) return FailRemote("scenes", 2, args.status());
  absl::StatusOr<std::unique_ptr<client::Client>> c = ConnectFromFlags(*args);
  if (!c.ok()) return FailRemote("scenes", 2, c.status());
  if (auto name = args->Get("load")) {
    absl::StatusOr<v1::Scene> s = (*c)->LoadScene(*name, true);
    if (!s.ok()) return FailRemote("scenes", CodeFor(s.status()), s.status());
    std::printf("%s: %s, %llu Gaussians\n", s->name().c_str(), SceneStateName(s->state()),
                static_cast<unsigned long long>(s->num_gaussians()));
    return 0;
  }
  if (auto name = args->Get("unload")) {
    absl::Status s = (*c)->UnloadScene(*name);
    return s.ok() ? 0 : FailRemote("scenes", CodeFor(s), s);
  }
  if (auto name = args->Get("info")) {
    absl::StatusOr<v1::Scene> s = (*c)->GetScene(*name);
    if (!s.ok()) return FailRemote("scenes", CodeFor(s.status()), s.status());
    std::printf("%s\n", s->DebugString().c_str());
    return 0;
  }
  absl::StatusOr<v1::ServerInfo> info = (*c)->GetServerInfo();
  if (!info.ok()) return FailRemote("scenes", CodeFor(info.status()), info.status());
  absl::StatusOr<std::vector<v1::Scene>> scenes = (*c)->ListScenes();
  if (!scenes.ok()) return FailRemote("scenes", CodeFor(scenes.status()), scenes.status());
  std::printf("server %s: api %s, %s (%s), %d sessions, %d scenes loaded\n", args->Get("server").value_or("127.0.0.1:50051").c_str(),
              info->api_version().c_str(), info->backend().c_str(), info->device().c_str(),
              info->load().sessions(), info->load().scenes_loaded());
  std::printf("%-40s %-10s %-6s %-24s %s\n", "NAME", "STATE", "SOURCE", "TIME RANGE (us)", "CAMERAS");
  for (const v1::Scene& s : *scenes) {
    std::string range = s.has_time_range() ? absl::StrCat(s.start_time_us(), "..", s.end_time_us()) : "static";
    std::string cams;
    for (const auto& cam : s.rig().cameras()) {
      absl::StrAppend(&cams, cams.empty() ? "" : ",", cam.sensor_id(), "(", cam.intrinsics().width(), "x",
                      cam.intrinsics().height(), ")");
    }
    std::printf("%-40s %-10s %-6s %-24s %s\n", s.name().c_str(), SceneStateName(s.state()),
                s.source() == "job" ? "job" : "data", range.c_str(), cams.c_str());
  }
  return 0;
}

// `jobs train`'s settings, spelled as `streetsim train`'s (its flags, --set, --preset and
// --config's settings), into the job's preset and settings map (a later value wins). Only the
// syntax is checked here; the server checks the values with the trainer's own definitions.
static absl::Status TrainingConfigFromFlags(const ParsedArgs& args, v1::TrainingConfig* c) {
  absl::StatusOr<train::config::CommandLineConfig> given = TrainCommandLineConfig(args);
  if (!given.ok()) return given.status();
  if (given->config_path) {
    return absl::InvalidArgumentError("--config: a job takes --preset and settings (--set NAME=VALUE, --NAME VALUE)");
  }
  if (given->preset) c->set_preset(*given->preset);
  for (const auto& g : given->values) (*c->mutable_settings())[g.name] = g.text;
  if (auto v = args.Get("continue-from")) c->set_continue_from_scene(*v);
  return absl::OkStatus();
}

static std::vector<FlagSpec> JobsFlagSpecs() {
  std::vector<FlagSpec> specs = {{"scene-name"}, {"request-id"}, {"watch", false}, {"max-iterations"},
                                 {"continue-from"}};
  for (const FlagSpec& f : TrainSettingFlagSpecs()) specs.push_back(f);
  return specs;
}

int RunJobsCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args =
      ParsedArgs::Parse(argv, WithConnection(JobsFlagSpecs()));
  if (!args.ok()) return FailRemote("jobs", 2, args.status());
  const std::vector<std::string>& pos = args->positional();
  const std::string verb = pos.empty() ? "list" : pos[0];
  absl::StatusOr<std::unique_ptr<client::Client>> c = ConnectFromFlags(*args);
  if (!c.ok()) return FailRemote("jobs", 2, c.status());
  auto watch = [&](const std::string& id) -> int {
    absl::StatusOr<v1::Job> done = (*c)->WatchJob(id, ProgressBar);
    std::fprintf(stderr, "\n");
    if (!done.ok()) return FailRemote("jobs", CodeFor(done.status()), done.status());
    PrintJob(*done);
    return done->state() == v1::JOB_STATE_SUCCEEDED ? 0 : 1;
  };
  if (verb == "list" && pos.size() <= 1) {
    absl::StatusOr<std::vector<v1::Job>> jobs = (*c)->ListJobs();
    if (!jobs.ok()) return FailRemote("jobs", CodeFor(jobs.status()), jobs.status());
    for (const v1::Job& j : *jobs) PrintJob(j);
    return 0;
  }
  if (verb == "train" && pos.size() == 2) {
    v1::CreateTrainingJobRequest req;
    req.set_log_path(pos[1]);
    req.mutable_config()->set_scene_name(args->Get("scene-name").value_or(""));
    req.set_request_id(args->Get("request-id").value_or(""));
    if (auto it = args->Get("max-iterations")) {
      int n;
      if (!absl::SimpleAtoi(*it, &n) || n < 0) return FailRemote("jobs", 2, absl::InvalidArgumentError("--max-iterations takes an integer >= 0"));
      req.mutable_config()->set_max_iterations(n);
    }
    if (absl::Status s = TrainingConfigFromFlags(*args, req.mutable_config()); !s.ok()) return FailRemote("jobs", 2, s);
    // No settings and no --max-iterations: the default preset, as `streetsim train` runs it
    // (--max-iterations 0: init only).
    if (!args->Has("max-iterations") && req.config().preset().empty() && req.config().settings().empty()) {
      req.mutable_config()->set_preset(train::config::kDefaultPreset);
    }
    absl::StatusOr<v1::Job> job = (*c)->CreateTrainingJob(req);
    if (!job.ok()) return FailRemote("jobs", CodeFor(job.status()), job.status());
    PrintJob(*job);
    return args->Has("watch") ? watch(job->job_id()) : 0;
  }
  if ((verb == "watch" || verb == "cancel" || verb == "get") && pos.size() == 2) {
    if (verb == "watch") return watch(pos[1]);
    absl::StatusOr<v1::Job> job = verb == "cancel" ? (*c)->CancelJob(pos[1]) : (*c)->GetJob(pos[1]);
    if (!job.ok()) return FailRemote("jobs", CodeFor(job.status()), job.status());
    PrintJob(*job);
    return 0;
  }
  return FailRemote("jobs", 2, absl::InvalidArgumentError(
      "usage: streetsim jobs [list | train LOG_PATH [--scene-name N] [--request-id R] [--preset NAME] "
      "[--set NAME=VALUE]... [streetsim train's setting flags] [--continue-from SCENE] [--watch] | "
      "watch ID | get ID | cancel ID] [--server HOST:PORT]"));
}

// render --server --lidar: one sweep from the scene's log pose at --time-us (docs/server.md).
static int RunRemoteLidarRender(const ParsedArgs& args) {
  const std::string scene = args.Get("scene").value_or("");
  if (scene.empty()) return FailRemote("render", 2, absl::InvalidArgumentError("--scene NAME is required with --server --lidar"));
  absl::StatusOr<std::string> out_range = args.Required("out-range");
  if (!out_range.ok()) return FailRemote("render", 2, out_range.status());
  v1::RenderRequest req;
  req.set_scene(scene);
  req.set_no_cameras(true);
  if (auto t = args.Get("time-us")) {
    int64_t v;
    if (!absl::SimpleAtoi(*t, &v)) return FailRemote("render", 2, absl::InvalidArgumentError("--time-us takes an integer"));
    req.set_time_us(v);
  }
  int columns = 2048;
  if (auto c = args.Get("columns"); c && !absl::SimpleAtoi(*c, &columns)) {
    return FailRemote("render", 2, absl::InvalidArgumentError("--columns takes an integer"));
  }
  req.mutable_lidar()->set_columns(columns);  // the server validates the range
  absl::StatusOr<std::unique_ptr<client::Client>> c = ConnectFromFlags(args);
  if (!c.ok()) return FailRemote("render", 2, c.status());
  absl::StatusOr<v1::RenderResponse> resp = (*c)->Render(req);
  if (!resp.ok()) return FailRemote("render", CodeFor(resp.status()), resp.status());
  absl::StatusOr<client::DecodedLidar> lidar = client::DecodeLidar(resp->lidar());
  if (!lidar.ok()) return FailRemote("render", 1, lidar.status());
  if (absl::Status s = WriteFloatTiff(*out_range, lidar->columns, lidar->beams, lidar->range); !s.ok()) {
    return FailRemote("render", 1, s);
  }
  size_t returns = 0;
  for (float r : lidar->range) returns += r > 0;
  const v1::LidarTimings& t = resp->lidar().timings();
  std::fprintf(stderr,
               "streetsim render: LiDAR %dx%d of %s on the server: %zu returns, %.1f ms (sweep %.1f: projection %.1f, "
               "sort %.1f, blend %.1f; queue %.1f), %s\n",
               lidar->beams, lidar->columns, scene.c_str(), returns, resp->timings().total_ms(), t.total_ms(),
               t.projection_ms(), t.sort_ms(), t.blend_ms(), resp->timings().queue_ms(),
               resp->lidar().digest().c_str());
  return 0;
}

int RunRemoteRenderCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(
      argv, WithConnection({{"ply"}, {"scene"}, {"camera"}, {"out-rgb"}, {"out-depth"}, {"out-alpha"},
                            {"background"}, {"backend"}, {"time-us"},
                            {"lidar", false}, {"columns"}, {"out-range"}}));
  if (!args.ok()) return FailRemote("render", 2, args.status());
  if (args->Has("lidar")) return RunRemoteLidarRender(*args);
  if (!args->positional().empty()) {
    return FailRemote("render", 2, absl::InvalidArgumentError(absl::StrCat("unexpected argument '", args->positional()[0], "'")));
  }
  // --ply with --server names a .ply under the server's data root (its scene name is the path
  // without ".ply"); --scene names any server scene.
  std::string scene = args->Get("scene").value_or("");
  if (auto ply = args->Get("ply")) {
    if (!scene.empty()) return FailRemote("render", 2, absl::InvalidArgumentError("give --scene or --ply, not both"));
    scene = *ply;
    if (absl::EndsWith(scene, ".ply")) scene.resize(scene.size() - 4);
  }
  if (scene.empty()) return FailRemote("render", 2, absl::InvalidArgumentError("--scene NAME (or --ply) is required with --server"));
  absl::StatusOr<std::string> camera_path = args->Required("camera");
  if (!camera_path.ok()) return FailRemote("render", 2, camera_path.status());
  absl::StatusOr<std::string> out_rgb = args->Required("out-rgb");
  if (!out_rgb.ok()) return FailRemote("render", 2, out_rgb.status());
  const std::string ext = absl::AsciiStrToLower(fs::path(*out_rgb).extension().string());
  if (ext != ".png" && ext != ".jpg" && ext != ".jpeg") {
    return FailRemote("render", 2, absl::InvalidArgumentError(absl::StrCat("--out-rgb ", *out_rgb, ": unsupported extension")));
  }
  absl::StatusOr<PinholeCamera> camera = ReadCameraJson(*camera_path);
  if (!camera.ok()) return FailRemote("render", 2, camera.status());
  v1::RenderRequest req;
  req.set_scene(scene);
  if (auto t = args->Get("time-us")) {
    int64_t v;
    if (!absl::SimpleAtoi(*t, &v)) return FailRemote("render", 2, absl::InvalidArgumentError("--time-us takes an integer"));
    req.set_time_us(v);
  }
  v1::SensorRequest* sensor = req.add_sensors();
  sensor->set_sensor_id("cli_camera");
  v1::PinholeIntrinsics* k = sensor->mutable_intrinsics();
  k->set_width(camera->width);
  k->set_height(camera->height);
  k->set_fx(camera->fx);
  k->set_fy(camera->fy);
  k->set_cx(camera->cx);
  k->set_cy(camera->cy);
  *sensor->mutable_t_ego_from_sensor() = client::ToPose(Eigen::Isometry3d::Identity());
  *req.mutable_t_world_from_sensor() = client::ToPose(camera->T_world_from_cam);
  v1::OutputSpec* out = req.mutable_outputs();
  out->set_rgb(true);
  out->set_rgb_encoding(ext == ".png" ? v1::IMAGE_ENCODING_PNG : v1::IMAGE_ENCODING_JPEG);
  out->set_depth(args->Has("out-depth"));
  out->set_alpha(args->Has("out-alpha"));
  if (auto bg = args->Get("background")) {
    const std::vector<std::string> parts = absl::StrSplit(*bg, ',');
    double v[3];
    if (parts.size() != 3 || !absl::SimpleAtod(parts[0], &v[0]) || !absl::SimpleAtod(parts[1], &v[1]) ||
        !absl::SimpleAtod(parts[2], &v[2])) {
      return FailRemote("render", 2, absl::InvalidArgumentError("--background takes R,G,B (three numbers in [0,1])"));
    }
    out->mutable_background_rgb()->set_x(v[0]);
    out->mutable_background_rgb()->set_y(v[1]);
    out->mutable_background_rgb()->set_z(v[2]);
  }
  if (args->Has("backend")) std::fprintf(stderr, "streetsim render: --backend is chosen by the server; ignored\n");
  absl::StatusOr<std::unique_ptr<client::Client>> c = ConnectFromFlags(*args);
  if (!c.ok()) return FailRemote("render", 2, c.status());
  absl::StatusOr<v1::RenderResponse> resp = (*c)->Render(req);
  if (!resp.ok()) return FailRemote("render", CodeFor(resp.status()), resp.status());
  const v1::SensorFrame& f = resp->frames(0);
  if (absl::Status s = checked_file::WriteAtomically(*out_rgb, f.rgb().data()); !s.ok()) return FailRemote("render", 1, s);
  if (auto p = args->Get("out-depth")) {
    if (absl::Status s = WriteFloatImage(*p, f.depth()); !s.ok()) return FailRemote("render", 1, s);
  }
  if (auto p = args->Get("out-alpha")) {
    if (absl::Status s = WriteFloatImage(*p, f.alpha()); !s.ok()) return FailRemote("render", 1, s);
  }
  std::fprintf(stderr, "streetsim render: %dx%d of %s on the server: %.1f ms (queue %.1f, render %.1f, encode %.1f), %s\n",
               f.rgb().width(), f.rgb().height(), scene.c_str(), resp->timings().total_ms(),
               resp->timings().queue_ms(), resp->timings().render_ms(), resp->timings().encode_ms(),
               resp->content_digest().c_str());
  return 0;
}

// SCENARIO.json:
// {"server": "127.0.0.1:50051", "scene": NAME, "num_steps": N, "step_dt_us": 100000,
//  "start_time_us": T0 (optional), "sensors": ["cam_front"] (optional), "width": W, "height": H,
//  "depth": false, "jpeg": false, "video_fps": 10,
//  "ego": {"mode": "log", "lateral_offset_m": 0.0, "longitudinal_offset_m": 0.0}
//       | {"mode": "poses", "poses": [[16 numbers], ...]}            (one per step)
//       | {"mode": "straight", "start": [16 numbers], "speed_mps": 5}}
// Writes OUT/frames/step_%05d_<sensor>.png|jpg, OUT/<sensor>.avi (MJPG) and OUT/summary.json.
int RunReplayCommand(const std::vector<std::string>& argv) {
  absl::StatusOr<ParsedArgs> args = ParsedArgs::Parse(argv, WithConnection({{"out"}}));
  if (!args.ok()) return FailRemote("replay", 2, args.status());
  if (args->positional().size() != 1) {
    return FailRemote("replay", 2,
                absl::InvalidArgumentError("usage: streetsim replay SCENARIO.json --out DIR [--server HOST:PORT]"));
  }
  const std::string out_dir = args->Get("out").value_or("replay-out");
  absl::StatusOr<ReplayScenario> sc = ReadReplayScenario(args->positional()[0]);
  if (!sc.ok()) return FailRemote("replay", 2, sc.status());
  ParsedArgs conn = *args;
  if (!args->Has("server") && sc->server) {
    std::vector<std::string> a = {"--server", *sc->server};
    absl::StatusOr<ParsedArgs> parsed = ParsedArgs::Parse(a, kConnectionFlags);
    if (!parsed.ok()) return FailRemote("replay", 2, parsed.status());
    conn = *parsed;
  }
  absl::StatusOr<std::unique_ptr<client::Client>> c = ConnectFromFlags(conn);
  if (!c.ok()) return FailRemote("replay", 2, c.status());
  // A scene lists its actors once loaded: a scenario that edits them loads it first.
  if (!sc->actors.is_null()) {
    absl::StatusOr<v1::Scene> loaded = (*c)->LoadScene(sc->scene, true);
    if (!loaded.ok()) return FailRemote("replay", CodeFor(loaded.status()), loaded.status());
  }
  absl::StatusOr<v1::Scene> info = (*c)->GetScene(sc->scene);
  if (!info.ok()) return FailRemote("replay", CodeFor(info.status()), info.status());
  std::vector<std::string> sensor_ids;
  v1::CreateSessionRequest create = ScenarioSession(*sc, *info, &sensor_ids);
  const int64_t dt = create.step_dt_us();
  const int64_t t0 =
      create.start_time_us() == 0 && info->has_time_range() ? info->start_time_us() : create.start_time_us();
  absl::StatusOr<std::vector<Eigen::Isometry3d>> poses = ScenarioEgoPoses(*sc, *info, t0);
  if (!poses.ok()) return FailRemote("replay", 2, poses.status());
  *create.mutable_initial_t_world_from_ego() = client::ToPose((*poses)[0]);
  std::vector<ScenarioEdit> actor_edits;
  if (!sc->actors.is_null()) {
    absl::StatusOr<std::vector<ScenarioEdit>> e = ScenarioActorEdits(sc->actors, *info, *poses, t0, dt);
    if (!e.ok()) return FailRemote("replay", 2, e.status());
    actor_edits = std::move(*e);
  }
  // The edits in force at step k: those from a step at or before it.
  const auto edits_at = [&](int k) {
    v1::ActorEdits in_force;
    for (const ScenarioEdit& e : actor_edits) {
      if (e.from_step <= k) *in_force.add_edits() = e.edit;
    }
    return in_force;
  };

  absl::StatusOr<v1::Session> session = (*c)->CreateSession(create);
  if (!session.ok()) return FailRemote("replay", CodeFor(session.status()), session.status());
  std::error_code ec;
  fs::create_directories(fs::path(out_dir) / "frames", ec);
  if (ec) return FailRemote("replay", 2, absl::InvalidArgumentError(absl::StrCat("--out ", out_dir, ": ", ec.message())));
  std::map<std::string, cv::VideoWriter> videos;
  const double fps = sc->video_fps.value_or(1e6 / dt);
  json steps = json::array();
  std::vector<double> latencies;
  for (int k = 0; k < sc->num_steps; ++k) {
    v1::StepRequest step;
    step.set_session_id(session->session_id());
    step.set_step_index(k);
    *step.mutable_t_world_from_ego() = client::ToPose((*poses)[k]);
    if (!actor_edits.empty()) {
      const v1::ActorEdits now = edits_at(k);
      if (k == 0 || now.edits_size() != edits_at(k - 1).edits_size()) *step.mutable_actor_edits() = now;
    }
    const auto t_start = std::chrono::steady_clock::now();
    absl::StatusOr<v1::StepResponse> r = (*c)->Step(step);
    if (!r.ok() && absl::IsUnavailable(r.status())) r = (*c)->Step(step);  // idempotent retry
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_start).count();
    if (!r.ok()) {
      (void)(*c)->CloseSession(session->session_id());
      return FailRemote("replay", CodeFor(r.status()), r.status());
    }
    latencies.push_back(ms);
    absl::StatusOr<json> frames = WriteStepFrames(*r, k, sc->jpeg, out_dir, fps, &videos);
    if (!frames.ok()) return FailRemote("replay", 1, frames.status());
    const auto& tr = r->t_world_from_ego().translation_m();
    steps.push_back({{"step_index", r->step_index()}, {"time_us", r->time_us()},
                     {"ego_xyz_m", {tr.x(), tr.y(), tr.z()}}, {"latency_ms", ms},
                     {"server_total_ms", r->timings().total_ms()}, {"content_digest", r->content_digest()},
                     {"frames", *frames}});
  }
  for (auto& [id, vw] : videos) vw.release();
  (void)(*c)->CloseSession(session->session_id());
  double mean = 0;
  for (double l : latencies) mean += l / latencies.size();
  json summary = {{"scenario", args->positional()[0]}, {"scene", sc->scene}, {"session", session->session_id()},
                  {"num_steps", sc->num_steps}, {"step_dt_us", dt}, {"sensors", sensor_ids},
                  {"step_latency_ms", {{"mean", mean}, {"p50", Percentile(latencies, 0.5)},
                                       {"p99", Percentile(latencies, 0.99)}}},
                  {"videos", json::array()}, {"steps", steps}};
  for (auto& [id, vw] : videos) summary["videos"].push_back(id + ".avi");
  if (absl::Status s = checked_file::WriteAtomically((fs::path(out_dir) / "summary.json").string(), summary.dump(1));
      !s.ok()) {
    return FailRemote("replay", 1, s);
  }
  std::fprintf(stderr, "streetsim replay: %d steps of %s, step latency p50 %.1f ms p99 %.1f ms; wrote %s/\n",
               sc->num_steps, sc->scene.c_str(), Percentile(latencies, 0.5), Percentile(latencies, 0.99),
               out_dir.c_str());
  return 0;
}

}  // namespace streetsim
