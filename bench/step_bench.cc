// Closed-loop step latency end to end (issue "Real-time closed loop"): an in-process
// `streetsim serve` on 127.0.0.1, S sessions each stepping K times over gRPC, every step at a new
// time, camera (RGB + depth) and LiDAR per step. Prints a table and, as its last line, one JSON
// object (p50_ms, p99_ms, steps_per_s, rss_mib ...). Figures: docs/benchmarks.md "Server step latency".
//
//   step_bench [--field none|exact|served] [--gaussians N | --scene DIR] [--camera WxH] [--lidar BEAMSxCOLUMNS]
//              [--steps K] [--warmup W] [--sessions S] [--actor-edit none|remove|move|insert]
//              [--backend cpu|vulkan] [--field-device auto|cpu|vulkan]
//
// --gaussians N: a synthetic street whose field moves every Gaussian (its time planes vary over
// the whole scene, as a trained KITTI field does: docs/benchmarks.md "On trained KITTI scenes").
// --scene DIR: a trained scene directory (scene.ply, field.bin, scene.json); --field none serves
// its Gaussians without the field. --field exact: the field's network per step (serve
// --field-serving exact); served: its serving form (scene/field/serving_form.h), built at the first
// load (load_s includes it) and cached beside the scene. --lidar 0x0: no LiDAR.
// --actor-edit: every step edits the scene's largest actor (--scene DIR with actors.json,
// docs/actors.md): removes it, moves it 3.5 m to its left, or inserts a copy there.
// --warmup W (default 1): each session's first W steps (first-use allocations, caches) are timed
// apart: `first_step_ms` is the slowest of them; p50 / p99 are over the K steps after them.
// --backend vulkan: the server's render engine on Vulkan (a GPU when there is one, else lavapipe);
// --field-device as `streetsim serve`'s (vulkan with the serving form: the form's kernel writes
// the engine's scene, render/vulkan/field/vulkan_serving_form.h). The JSON's field_device is
// where the served scene ended up (GetScene).
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "client/cpp/streetsim_client.h"
#include "scene/field/field_io.h"
#include "scene/gaussians/ply_io.h"
#include "scene/gaussians/synthetic_street.h"
#include "scene/train/dynamic_stage.h"
#include "server/server.h"
#include "server/server_main.h"

using namespace streetsim;
namespace fs = std::filesystem;
namespace v1 = streetsim::v1;

namespace {

struct Args {
  std::string field = "exact";
  int gaussians = 500000;
  std::string scene_dir;
  int width = 1242, height = 375;
  int beams = 64, columns = 2048;
  int steps = 20;
  int warmup = 1;
  int sessions = 1;
  std::string actor_edit = "none";
  std::string backend = "cpu";       // the render engine (--backend)
  std::string field_device = "auto";  // --field-device, as `streetsim serve`'s
};

int Usage(const char* why) {
  std::fprintf(stderr,
               "step_bench: %s\nusage: step_bench [--field none|exact|served] [--gaussians N | --scene DIR] "
               "[--camera WxH] [--lidar BEAMSxCOLUMNS] [--steps K] [--warmup W] [--sessions S] "
               "[--actor-edit none|remove|move|insert] [--backend cpu|vulkan] [--field-device auto|cpu|vulkan]\n",
               why);
  return 2;
}

bool ParsePair(const char* s, int* a, int* b) { return std::sscanf(s, "%dx%d", a, b) == 2 && *a >= 0 && *b >= 0; }

// The spec-size field with every time plane varying in time everywhere: every Gaussian moves.
field::DeformationField MovingEverywhere(const GaussianStore& g, int64_t end_us) {
  absl::StatusOr<field::DeformationField> f =
      field::DeformationField::Create(field::FieldConfig{}, train::AabbOfMeans(g.means), {0, end_us}, 3);
  if (!f.ok()) std::abort();
  const field::FieldLayout& L = f->layout();
  for (const field::PlaneInfo& pi : L.planes) {
    if (!field::PlaneHasTime(pi.plane)) continue;
    for (int v = 0; v < pi.height; ++v)
      for (int u = 0; u < pi.width; ++u)
        for (int k = 0; k < L.channels; ++k)
          f->mutable_params()[pi.offset + (size_t(v) * pi.width + u) * L.channels + k] =
              1.0f + 0.5f * std::sin(1.3f * v + 0.7f * u + k);
  }
  return std::move(*f);
}

std::string TempDir(const char* tag) {
  std::string t = (fs::temp_directory_path() / (std::string("step_bench_") + tag + "_XXXXXX")).string();
  return mkdtemp(t.data());
}

double RssMib() {
  std::ifstream in("/proc/self/statm");
  long pages_total = 0, pages_rss = 0;
  in >> pages_total >> pages_rss;
  return pages_rss * double(sysconf(_SC_PAGESIZE)) / (1 << 20);
}

// Hard links of a trained scene's files (same file system) or copies, without field.bin for
// --field none.
bool LinkScene(const std::string& from, const std::string& to, bool with_field) {
  fs::create_directories(to);
  for (const char* name : {"scene.ply", "scene.json", "field.bin", "field_ext.bin", "field.serving", "train_meta.json",
                           "actors.json", "actors.ply"}) {
    const fs::path src = fs::path(from) / name;
    if (!fs::exists(src) || (!with_field && std::string(name).rfind("field", 0) == 0)) continue;
    std::error_code ec;
    fs::create_hard_link(src, fs::path(to) / name, ec);
    if (ec) fs::copy_file(src, fs::path(to) / name, ec);
    if (ec) return false;
  }
  return fs::exists(fs::path(to) / "scene.ply");
}

}  // namespace

int main(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string flag = argv[i];
    if (i + 1 >= argc) return Usage(("missing value after " + flag).c_str());
    const char* v = argv[++i];
    if (flag == "--field") a.field = v;
    else if (flag == "--gaussians") a.gaussians = std::atoi(v);
    else if (flag == "--scene") a.scene_dir = v;
    else if (flag == "--camera") { if (!ParsePair(v, &a.width, &a.height)) return Usage("--camera takes WxH"); }
    else if (flag == "--lidar") { if (!ParsePair(v, &a.beams, &a.columns)) return Usage("--lidar takes BEAMSxCOLUMNS"); }
    else if (flag == "--steps") a.steps = std::atoi(v);
    else if (flag == "--warmup") a.warmup = std::atoi(v);
    else if (flag == "--sessions") a.sessions = std::atoi(v);
    else if (flag == "--actor-edit") a.actor_edit = v;
    else if (flag == "--backend") a.backend = v;
    else if (flag == "--field-device") a.field_device = v;
    else return Usage(("unknown flag " + flag).c_str());
  }
  if (a.field != "none" && a.field != "exact" && a.field != "served") return Usage("--field takes none, exact or served");
  if (a.actor_edit != "none" && a.actor_edit != "remove" && a.actor_edit != "move" && a.actor_edit != "insert") {
    return Usage("--actor-edit takes none, remove, move or insert");
  }
  if (a.actor_edit != "none" && a.scene_dir.empty()) return Usage("--actor-edit needs --scene DIR with actors");
  const bool with_field = a.field != "none";
  if (a.beams != 0 && a.beams != 64) return Usage("--lidar: the served LiDAR is the HDL-64E table (64 beams)");
  if (a.gaussians < 1 || a.steps < 1 || a.sessions < 1 || a.width < 1 || a.height < 1) {
    return Usage("--gaussians, --steps, --sessions and --camera must be positive");
  }
  if (a.warmup < 0 || a.warmup > 1000) return Usage("--warmup takes 0..1000");
  absl::StatusOr<Backend> backend = ParseBackend(a.backend);
  if (!backend.ok() || *backend == Backend::kAuto) return Usage("--backend takes cpu or vulkan");
  absl::StatusOr<train::FieldDevice> field_device = train::ParseFieldDevice(a.field_device);
  if (!field_device.ok()) return Usage("--field-device takes auto, cpu or vulkan");

  const std::string root = TempDir("data"), state = TempDir("state");
  const std::string scene_path = root + "/bench";
  int64_t end_us = 10'000'000;
  if (a.scene_dir.empty()) {
    SyntheticStreetOptions so;
    so.num_gaussians = a.gaussians;
    so.sh_degree = 3;
    const GaussianStore g = MakeSyntheticStreet(so);
    fs::create_directories(scene_path);
    if (!WriteGaussianPly(g, scene_path + "/scene.ply").ok()) return 1;
    std::ofstream(scene_path + "/scene.json") << "{\"time_range_us\": [0, " << end_us << "]}";
    if (with_field && !field::SaveField(MovingEverywhere(g, end_us), scene_path + "/field.bin").ok()) return 1;
  } else if (!LinkScene(a.scene_dir, scene_path, with_field)) {
    return Usage(("--scene " + a.scene_dir + ": no scene.ply there").c_str());
  }

  server::ConfigureServingAllocator();  // as `streetsim serve` runs (rss_mib measures what it holds)
  server::ServerOptions o;
  o.listen = "127.0.0.1:0";
  o.data_root = root;
  o.state_dir = state;
  o.backend = *backend;
  o.field_device = *field_device;
  o.exact_field = a.field == "exact";
  o.limits.max_sessions = std::max(16, a.sessions);
  o.limits.max_queued_renders = std::max(8, a.sessions);
  absl::StatusOr<std::unique_ptr<server::Server>> srv = server::Server::Start(o);
  if (!srv.ok()) return std::fprintf(stderr, "step_bench: %s\n", std::string(srv.status().message()).c_str()), 1;
  client::ClientOptions co;
  co.target = (*srv)->address();
  co.timeout_s = 600;
  absl::StatusOr<std::unique_ptr<client::Client>> c = client::Client::Connect(co);
  if (!c.ok()) return 1;
  absl::StatusOr<v1::Scene> loaded = (*c)->LoadScene("bench", true);
  if (!loaded.ok() || loaded->state() != v1::SCENE_STATE_READY) {
    std::fprintf(stderr, "step_bench: the scene did not load: %s\n",
                 loaded.ok() ? loaded->error().c_str() : std::string(loaded.status().message()).c_str());
    return 1;
  }
  const double rss_loaded = RssMib();
  if (loaded->has_time_range()) end_us = loaded->end_time_us() - loaded->start_time_us();

  // The edit every step makes: on the actor with the most Gaussians.
  std::optional<v1::ActorEdit> edit;
  if (a.actor_edit != "none") {
    absl::StatusOr<v1::Scene> info = (*c)->GetScene("bench");
    if (!info.ok() || info->actors().empty()) return Usage("--actor-edit: the scene has no actors (actors.json)");
    const v1::Actor* big = &info->actors(0);
    for (const v1::Actor& actor : info->actors()) {
      if (actor.num_gaussians() > big->num_gaussians()) big = &actor;
    }
    edit.emplace();
    edit->set_actor_id(big->actor_id());
    edit->set_kind(a.actor_edit == "remove" ? v1::ACTOR_EDIT_REMOVE
                   : a.actor_edit == "move" ? v1::ACTOR_EDIT_MOVE
                                            : v1::ACTOR_EDIT_INSERT);
    if (a.actor_edit != "remove") {
      for (const v1::ActorPose& p : big->trajectory()) {
        Eigen::Isometry3d T = client::FromPose(p.t_world_from_actor());
        T.translation() += T.linear() * Eigen::Vector3d(0, 3.5, 0);
        v1::ActorPose* q = edit->add_trajectory();
        q->set_time_us(p.time_us());
        *q->mutable_t_world_from_actor() = client::ToPose(T);
      }
    }
  }

  std::mutex mu;
  std::vector<double> latencies_ms;  // the steps after the warm-up
  double first_step_ms = 0;          // the slowest warm-up step
  size_t steps_done = 0;             // every step answered, warm-up included (steps/s)
  int errors = 0;
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<std::thread> threads;
  for (int s = 0; s < a.sessions; ++s) {
    threads.emplace_back([&, s] {
      absl::StatusOr<std::unique_ptr<client::Client>> mine = client::Client::Connect(co);
      v1::CreateSessionRequest req;
      req.set_scene("bench");
      req.set_start_time_us(loaded->has_time_range() ? loaded->start_time_us() : 0);
      // Each step at a new time; sessions apart in time, as independent planners are.
      req.set_step_dt_us(std::max<int64_t>(1, end_us / (a.warmup + a.steps + 1)));
      v1::SensorRequest* cam = req.add_sensors();
      cam->set_sensor_id(loaded->rig().cameras_size() ? loaded->rig().cameras(0).sensor_id() : "cam_front");
      cam->set_width(a.width);
      cam->set_height(a.height);
      req.mutable_outputs()->set_rgb(true);
      req.mutable_outputs()->set_depth(true);
      if (a.beams > 0) req.mutable_lidar()->set_columns(a.columns);
      if (edit) *req.add_actor_edits() = *edit;
      absl::StatusOr<v1::Session> session = mine.ok() ? (*mine)->CreateSession(req) : mine.status();
      if (!session.ok()) {
        std::fprintf(stderr, "step_bench: session %d: %s\n", s, std::string(session.status().message()).c_str());
        std::lock_guard<std::mutex> l(mu);
        errors += a.warmup + a.steps;
        return;
      }
      for (int k = 0; k < a.warmup + a.steps; ++k) {
        v1::StepRequest step;
        step.set_session_id(session->session_id());
        step.set_step_index(k);
        Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
        ego.translation() = Eigen::Vector3d(0.3 * k + 0.05 * s, 0, 0);
        *step.mutable_t_world_from_ego() = client::ToPose(ego);
        const auto t = std::chrono::steady_clock::now();
        absl::StatusOr<v1::StepResponse> r = (*mine)->Step(step);
        const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t).count();
        std::lock_guard<std::mutex> l(mu);
        if (!r.ok()) {
          ++errors;
          continue;
        }
        ++steps_done;
        if (k < a.warmup) {
          first_step_ms = std::max(first_step_ms, ms);
        } else {
          latencies_ms.push_back(ms);
        }
      }
      (void)(*mine)->CloseSession(session->session_id());
    });
  }
  for (std::thread& t : threads) t.join();
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  absl::StatusOr<v1::Scene> after = (*c)->GetScene("bench");
  std::sort(latencies_ms.begin(), latencies_ms.end());
  const auto pct = [&](double p) {
    return latencies_ms.empty() ? NAN : latencies_ms[std::min(latencies_ms.size() - 1, size_t(p * latencies_ms.size()))];
  };
  const double rss = RssMib();
  const size_t n = loaded->num_gaussians();
  std::printf("| field | actor edit | Gaussians | moving | camera | LiDAR | sessions | steps | p50 ms | p99 ms | steps/s | errors | RSS MiB |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
  std::printf("| %s | %s | %zu | %llu | %dx%d | %dx%d | %d | %zu | %.1f | %.1f | %.2f | %d | %.0f |\n", a.field.c_str(),
              a.actor_edit.c_str(), n,
              static_cast<unsigned long long>(after.ok() ? after->num_dynamic_gaussians() : 0), a.width, a.height, a.beams,
              a.columns, a.sessions, latencies_ms.size(), pct(0.5), pct(0.99), steps_done / wall_s, errors, rss);
  std::printf("{\"field\": \"%s\", \"backend\": \"%s\", \"field_device\": \"%s\", \"actor_edit\": \"%s\", \"gaussians\": %zu, \"moving\": %llu, \"sessions\": %d, \"steps\": %zu, "
              "\"p50_ms\": %.2f, \"p99_ms\": %.2f, \"steps_per_s\": %.3f, \"errors\": %d, \"rss_mib\": %.1f, "
              "\"rss_loaded_mib\": %.1f, \"load_s\": %.2f, \"field_evaluations\": %lld, \"warmup_steps\": %d, "
              "\"first_step_ms\": %.2f}\n",
              a.field.c_str(), a.backend.c_str(), after.ok() ? after->field_device().c_str() : "", a.actor_edit.c_str(), n,
              static_cast<unsigned long long>(after.ok() ? after->num_dynamic_gaussians() : 0), a.sessions,
              latencies_ms.size(), pct(0.5), pct(0.99), steps_done / wall_s, errors, rss, rss_loaded,
              loaded->load_time_s(), static_cast<long long>(after.ok() ? after->field_evaluations() : 0), a.warmup,
              first_step_ms);
  c->reset();
  srv->reset();
  fs::remove_all(root);
  fs::remove_all(state);
  return errors ? 1 : 0;
}
