// Step latency of a dynamic scene (field.bin) against the same Gaussians without a field, one
// session, camera + LiDAR every step, every step a new timestamp (so the field runs every step).
// Prints the scenes' load times and a table. Usage:
//   field_serve_bench [--gaussians G] [--steps M] [--width W] [--height H] [--columns C (-1: no LiDAR)]
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "scene/field/field_io.h"
#include "scene/train/dynamic_stage.h"
#include "tests/server/server_fixture.h"

using namespace streetsim;
namespace v1 = streetsim::v1;

namespace {

// The spec-size field (FieldConfig{}) whose finest xt plane varies in time over a band of x
// (as bench/field_bench): Gaussians in the band move, the rest are baked at load.
field::DeformationField BandField(const GaussianStore& g) {
  absl::StatusOr<field::DeformationField> f =
      field::DeformationField::Create(field::FieldConfig{}, train::AabbOfMeans(g.means), {0, 10'000'000}, 3);
  if (!f.ok()) std::abort();
  const field::FieldLayout& L = f->layout();
  for (const field::PlaneInfo& pi : L.planes) {
    if (pi.plane != 2 || pi.level != L.num_levels - 1) continue;
    const int u0 = pi.width * 45 / 100, u1 = pi.width * 55 / 100;
    for (int v = 0; v < pi.height; ++v)
      for (int u = u0; u < u1; ++u)
        for (int k = 0; k < L.channels; ++k)
          f->mutable_params()[pi.offset + (size_t(v) * pi.width + u) * L.channels + k] = 1.0f + 0.8f * std::sin(2.0f * v + k);
  }
  return std::move(*f);
}

}  // namespace

int main(int argc, char** argv) {
  int gaussians = 100000, steps = 20, width = 640, height = 192, columns = 1024;
  for (int i = 1; i + 1 < argc; i += 2) {
    const int v = std::atoi(argv[i + 1]);
    if (!std::strcmp(argv[i], "--gaussians")) gaussians = v;
    else if (!std::strcmp(argv[i], "--steps")) steps = v;
    else if (!std::strcmp(argv[i], "--width")) width = v;
    else if (!std::strcmp(argv[i], "--height")) height = v;
    else if (!std::strcmp(argv[i], "--columns")) columns = v;
  }
  const std::string root = streetsim::testing::MakeTempDir("field_bench_data");
  const std::string state = streetsim::testing::MakeTempDir("field_bench_state");
  SyntheticStreetOptions so;
  so.num_gaussians = gaussians;
  so.sh_degree = 3;
  const GaussianStore g = MakeSyntheticStreet(so);
  for (const char* name : {"static", "dynamic"}) {
    std::filesystem::create_directories(root + "/" + name);
    if (!WriteGaussianPly(g, root + "/" + name + "/scene.ply").ok()) return 1;
  }
  if (!field::SaveField(BandField(g), root + "/dynamic/field.bin").ok()) return 1;
  auto srv = server::Server::Start(streetsim::testing::TestOptions(root, state));
  if (!srv.ok()) return 1;
  auto c = client::Client::Connect({.target = (*srv)->address(), .timeout_s = 600});
  if (!c.ok()) return 1;
  std::printf("| scene | Gaussians | dynamic | load s | steps | step p50 ms | step mean ms | max ms | field evaluations |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|\n");
  int errors = 0;
  for (const char* name : {"static", "dynamic", "static", "dynamic"}) {  // A/B/A/B back to back
    (void)(*c)->UnloadScene(name);
    if (!(*c)->LoadScene(name, true).ok()) return 1;
    v1::CreateSessionRequest req;
    req.set_scene(name);
    req.set_step_dt_us(100'000);
    auto* sensor = req.add_sensors();
    sensor->set_sensor_id("cam_front");
    sensor->set_width(width);
    sensor->set_height(height);
    if (columns >= 0) req.mutable_lidar()->set_columns(columns);
    auto session = (*c)->CreateSession(req);
    if (!session.ok()) return 1;
    std::vector<double> lat;
    for (int k = 0; k < steps; ++k) {
      v1::StepRequest step;
      step.set_session_id(session->session_id());
      step.set_step_index(k);
      Eigen::Isometry3d ego = Eigen::Isometry3d::Identity();
      ego.translation() = Eigen::Vector3d(0.5 * k, 0, 0);
      *step.mutable_t_world_from_ego() = client::ToPose(ego);
      const auto a = std::chrono::steady_clock::now();
      if (!(*c)->Step(step).ok()) ++errors;
      lat.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - a).count());
    }
    (void)(*c)->CloseSession(session->session_id());
    auto scene = (*c)->GetScene(name);
    if (!scene.ok()) return 1;
    double mean = 0;
    for (double l : lat) mean += l / lat.size();
    std::sort(lat.begin(), lat.end());
    std::printf("| %s | %d | %llu | %.2f | %d | %.1f | %.1f | %.1f | %lld |\n", name, gaussians,
                static_cast<unsigned long long>(scene->num_dynamic_gaussians()), scene->load_time_s(), steps,
                lat[lat.size() / 2], mean, lat.back(), static_cast<long long>(scene->field_evaluations()));
  }
  srv->reset();
  std::filesystem::remove_all(root);
  std::filesystem::remove_all(state);
  return errors ? 1 : 0;
}
